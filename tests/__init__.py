"""The test suite. Every test folder is a package, so pytest names each module by its path
(``tests.collector.test_cli``): two folders may hold same-named modules, and ``tests.collector``
never shadows the ``collector`` package under test. Shared helpers live in ``tests/support/``,
the one folder on pytest's ``pythonpath``; they are imported as plain modules (``loopback``)."""
