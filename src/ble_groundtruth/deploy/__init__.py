"""Fleet deployment helpers: the inventory reader, the site PKI and the Zenoh ACL generator.

Lives in the installed package (not only under ``deploy/``) because the collector's
``fleet`` CLI reads the same inventory on a host that has only the wheel.
"""
