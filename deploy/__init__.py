"""Fleet deployment helpers: the inventory reader, the site PKI and the Zenoh ACL generator.

They sit beside the Ansible playbook (``site.yml``, ``roles/``) whose control-machine steps they
are, and ship in the wheel too, because the collector's ``fleet`` CLI reads the same inventory
on a host that has only the wheel.
"""
