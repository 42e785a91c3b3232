"""What a host says about itself, in one round trip: a POSIX shell script (uptime, systemd and
the units, the site file and the fleetdaq command, free space and bytes under the spool and
data directories) and the parser of what it prints, one ``key value...`` line per fact.

Only POSIX sh, coreutils (``df -P``, ``stat -c``) and ``find``: what Raspberry Pi OS, Debian and
BusyBox all have.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass

from fleetdaq.fleet.layout import HostLayout

_SCRIPT = r"""LC_ALL=C; export LC_ALL
echo "uptime $(cut -d' ' -f1 /proc/uptime 2>/dev/null)"
if [ -d /run/systemd/system ] && command -v systemctl >/dev/null 2>&1; then
  echo "systemd yes"
  unit() {{
    state=$(systemctl show -p LoadState -p ActiveState -p SubState "$1" 2>/dev/null | tr '\n' ' ')
    printf 'unit %s %s\n' "$1" "$state"
  }}
  {units}
else
  echo "systemd no"
fi
if [ -r {site_file} ]; then echo "site_file yes"; else echo "site_file no"; fi
if [ -x {fleetdaq} ]; then echo "fleetdaq yes"; else echo "fleetdaq no"; fi
usage() {{
  p=$2
  while [ ! -d "$p" ]; do p=$(dirname "$p"); done
  echo "df $1 $(df -Pk "$p" 2>/dev/null | awk 'NR==2 {{print $2, $4}}')"
  if [ -d "$2" ]; then
    n=$(find "$2" -type f -exec stat -c %s {{}} + 2>/dev/null | awk '{{s+=$1}} END {{print s+0}}')
    echo "bytes $1 $n"
  else
    echo "bytes $1 -"
  fi
}}
{usage}
"""


@dataclass(frozen=True, slots=True)
class Unit:
    """A systemd unit's state (``systemctl show``)."""

    name: str
    load: str
    """``loaded``, ``not-found``, ..."""
    active: str
    """``active``, ``inactive``, ``failed``, ``activating``, ..."""
    sub: str
    """``running``, ``dead``, ``exited``, ..."""

    @property
    def ok(self) -> bool:
        return self.active == "active"

    def describe(self) -> str:
        if self.load == "not-found":
            return "not installed"
        return f"{self.active} ({self.sub})" if self.sub else self.active


@dataclass(frozen=True, slots=True)
class DirUsage:
    """A directory on the host: free space on its filesystem, bytes of the files under it."""

    role: str
    """``spool`` (an edge's) or ``data`` (the hub's recordings)."""
    path: str
    exists: bool
    total_bytes: int | None
    """Size of its filesystem (of its nearest existing parent when it does not exist)."""
    free_bytes: int | None
    """Available to the services (``df``'s Available)."""
    bytes: int | None
    """Bytes in the files under it; None when it does not exist."""

    @property
    def free_fraction(self) -> float | None:
        if not self.total_bytes or self.free_bytes is None:
            return None
        return self.free_bytes / self.total_bytes


@dataclass(frozen=True, slots=True)
class Facts:
    uptime_s: float | None
    systemd: bool
    units: tuple[Unit, ...]
    site_file: bool
    """The site file is there and readable."""
    fleetdaq: bool
    """The fleetdaq command is there and executable."""
    dirs: tuple[DirUsage, ...]


def facts_script(layout: HostLayout) -> str:
    """The shell script for a host with this layout."""
    usage = "\n".join(f"usage {role} {shlex.quote(p)}" for role, p in layout.dirs().items())
    return _SCRIPT.format(
        units="\n  ".join(f"unit {shlex.quote(u)}" for u in layout.units) or ":",
        site_file=shlex.quote(layout.site_file),
        fleetdaq=shlex.quote(layout.fleetdaq),
        usage=usage or ":",
    )


def _int(text: str) -> int | None:
    return int(text) if text.isdigit() else None


def parse_facts(text: str, layout: HostLayout) -> Facts:
    """What `facts_script` printed, parsed. Lines it does not know are ignored; facts that are
    missing stay None (an odd host gives a partial answer, not an error)."""
    uptime: float | None = None
    systemd = False
    units: list[Unit] = []
    site_file = fleetdaq = False
    df: dict[str, tuple[int | None, int | None]] = {}
    under: dict[str, int | None] = {}
    for line in text.splitlines():
        key, _, rest = line.partition(" ")
        if key == "uptime":
            try:
                uptime = float(rest)
            except ValueError:
                uptime = None
        elif key == "systemd":
            systemd = rest.strip() == "yes"
        elif key == "unit":
            name, _, props = rest.partition(" ")
            values = dict(p.partition("=")[::2] for p in props.split())
            units.append(
                Unit(
                    name,
                    values.get("LoadState", ""),
                    values.get("ActiveState", "unknown"),
                    values.get("SubState", ""),
                )
            )
        elif key == "site_file":
            site_file = rest.strip() == "yes"
        elif key == "fleetdaq":
            fleetdaq = rest.strip() == "yes"
        elif key == "df":
            role, *sizes = rest.split()
            if len(sizes) == 2 and all(s.isdigit() for s in sizes):
                df[role] = (int(sizes[0]) * 1024, int(sizes[1]) * 1024)
        elif key == "bytes":
            role, _, value = rest.partition(" ")
            under[role] = _int(value.strip())
    dirs = tuple(
        DirUsage(
            role=role,
            path=path,
            exists=under.get(role) is not None,
            total_bytes=df.get(role, (None, None))[0],
            free_bytes=df.get(role, (None, None))[1],
            bytes=under.get(role),
        )
        for role, path in layout.dirs().items()
    )
    return Facts(uptime, systemd, tuple(units), site_file, fleetdaq, dirs)
