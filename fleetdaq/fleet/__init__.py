"""``fleetdaq fleet``: every host of the site looked at over SSH (paramiko), from an Ansible
YAML inventory — one concern per module:

- `inventory`: the inventory file into typed hosts (Ansible's variable precedence);
- `site_match`: the inventory against a site file (every node has a host and back);
- `layout`: where fleetdaq's files are on a host (venv, site file, spool, recordings);
- `known_hosts`: known_hosts files read as ssh reads them;
- `ssh`: a verified SSH connection (never a key accepted silently) and its commands;
- `facts`: the shell script run on a host and the parsing of what it prints;
- `probe`: one host's status; `collect`: every host in parallel; `status`: what was found and
  the verdict;
- `report`: the table; `journal`: ``journalctl`` over SSH; `errors`: the error tree.
"""
