"""ansible/ passes ansible-lint's strictest profile (production), offline."""

from __future__ import annotations

import os
import subprocess

from tests.deploy.conftest import ANSIBLE, BIN


def test_ansible_lint_production_profile_passes(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("ANSIBLE_")}
    env.update(HOME=str(tmp_path), PATH=f"{BIN}:{env.get('PATH', '/usr/bin:/bin')}", NO_COLOR="1")
    r = subprocess.run(
        [str(BIN / "ansible-lint"), "--profile", "production", "--offline", "-f", "pep8"],
        cwd=ANSIBLE,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-4000:]
    assert "Profile 'production' was required, and it passed" in r.stderr + r.stdout
