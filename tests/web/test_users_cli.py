"""`fleetdaq users`: the dashboard's users file from the command line."""

from __future__ import annotations

import stat
import subprocess
import sys
from pathlib import Path

from argon2 import PasswordHasher

from hub.web.users import read_users
from tests.procs import REPO


def users(*args: str, stdin: str = "") -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fleetdaq", "users", *args],
        input=stdin, capture_output=True, text=True, cwd=REPO, timeout=60, check=False,
    )  # fmt: skip


def test_add_list_and_remove_users_in_a_0600_file(tmp_path: Path):
    path = tmp_path / "etc" / "users"
    r = users("add", "alice", "--file", str(path), "--password-stdin", stdin="tide-gauge-42\n")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == f"added alice in {path}"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert PasswordHasher().verify(read_users(path)["alice"], "tide-gauge-42")
    r = users("add", "bob", "--file", str(path), "--password-stdin", stdin="x" * 12)
    assert r.returncode == 0
    r = users("add", "alice", "--file", str(path), "--password-stdin", stdin="a-new-password\n")
    assert r.stdout.strip() == f"new password for alice in {path}"
    assert PasswordHasher().verify(read_users(path)["alice"], "a-new-password")
    assert users("list", "--file", str(path)).stdout.split() == ["alice", "bob"]
    assert users("remove", "bob", "--file", str(path)).returncode == 0
    assert users("list", "--file", str(path)).stdout.split() == ["alice"]


def test_the_site_files_users_file_is_used_with_config(tmp_path: Path):
    path = tmp_path / "site-users"
    site = tmp_path / "site.yaml"
    site.write_text(
        "site: s\nhub: {dashboard: {users_file: " + str(path) + "}}\n"
        "nodes: {a: {streams: {b: {driver: environment_sim, rate_hz: 1, "
        "channels: [{name: t, unit: degC}]}}}}\n"
    )
    r = users("add", "carol", "--config", str(site), "--password-stdin", stdin="lighthouse-7")
    assert r.returncode == 0, r.stderr
    assert list(read_users(path)) == ["carol"]


def test_bad_names_short_passwords_and_unknown_users_are_refused_in_one_line(tmp_path: Path):
    path = tmp_path / "users"
    r = users("add", "a b", "--file", str(path), "--password-stdin", stdin="long enough\n")
    assert (r.returncode, r.stderr.count("\n")) == (2, 1)
    assert "is not a user name" in r.stderr
    r = users("add", "dave", "--file", str(path), "--password-stdin", stdin="short\n")
    assert r.returncode == 2
    assert "at least 8 characters" in r.stderr
    assert not path.exists(), "nothing written"
    r = users("remove", "erin", "--file", str(path))
    assert r.returncode == 1
    assert "no user 'erin'" in r.stderr
    path.write_text("not a users file\n")
    r = users("add", "frank", "--file", str(path), "--password-stdin", stdin="long enough\n")
    assert r.returncode == 2
    assert "not NAME:ARGON2-HASH" in r.stderr
    assert path.read_text() == "not a users file\n", "a file it cannot read is left alone"
