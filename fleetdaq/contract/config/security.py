"""Security in the site file (`security:`): mutual TLS on every link and who may do what.

```yaml
security:
  tls: true                     # every link mutual TLS; endpoints are tls/HOST:PORT
  pki_dir: /etc/fleetdaq/pki    # where each machine finds ca.crt and its own certificate
  operators: {ann: control, bob: view}
```

With `tls` on, the hub's router admits only clients with a certificate from the site CA, and
its access control list (`fleetdaq.hub.routing.acl`, generated from this file, default deny) lets
each node publish only under its own keys, operators ask only the hub's services, and only control
operators command. Each machine's certificate: the hub's ``<pki_dir>/hub.crt``, partition hub P's
``<pki_dir>/partitions/P.crt`` (its own: it may speak only for its own nodes), node N's
``<pki_dir>/nodes/N.crt``, an operator's ``$FLEETDAQ_CERT`` / ``$FLEETDAQ_KEY`` or
``~/.config/fleetdaq/operator.crt`` (`fleetdaq pki` makes them all)."""

from __future__ import annotations

from typing import Literal

from fleetdaq.contract.schema import Name, Strict

Role = Literal["view", "control"]


class SecurityConfig(Strict):
    tls: bool = False
    """Mutual TLS and access control on every link (off: plain TCP, anyone on the network
    may publish, ack or command — only for a closed bench or loopback)."""
    pki_dir: str = "/etc/fleetdaq/pki"
    """``ca.crt``, ``hub.crt``/``hub.key``, ``partitions/<name>.crt``/``.key``,
    ``nodes/<node>.crt``/``.key`` (what `fleetdaq pki`
    writes; each machine needs the CA and its own pair only)."""
    operators: dict[Name, Role] = {}
    """People using the CLI: their certificate's name (``operator:NAME``) and role. view: the
    hub's status, lists and the alarm and recorder states; control: also ack, shelve, the
    recorder, and commanding outputs."""
