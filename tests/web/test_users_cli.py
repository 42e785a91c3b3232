"""`fleetdaq users`: the dashboard's users file from the command line."""

from __future__ import annotations

import stat
import subprocess
import sys
from pathlib import Path

from argon2 import PasswordHasher

from fleetdaq.hub.live.web.users import User, read_user_lines, read_users
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
    assert r.stdout.strip() == f"added alice (role view) in {path}"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert PasswordHasher().verify(read_users(path)["alice"], "tide-gauge-42")
    r = users("add", "bob", "--file", str(path), "--password-stdin", stdin="x" * 12)
    assert r.returncode == 0
    r = users("add", "alice", "--file", str(path), "--password-stdin", stdin="a-new-password\n")
    assert r.stdout.strip() == f"new password for alice (role view) in {path}"
    assert PasswordHasher().verify(read_users(path)["alice"], "a-new-password")
    assert users("list", "--file", str(path)).stdout.splitlines() == ["alice view", "bob view"]
    assert users("remove", "bob", "--file", str(path)).returncode == 0
    assert users("list", "--file", str(path)).stdout.splitlines() == ["alice view"]


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
    assert "not NAME:ROLE:ARGON2-HASH" in r.stderr
    assert path.read_text() == "not a users file\n", "a file it cannot read is left alone"


def test_a_new_user_looks_unless_given_control_and_a_new_password_keeps_the_role(tmp_path: Path):
    path = tmp_path / "users"
    r = users("add", "ops", "--role", "control", "--file", str(path), "--password-stdin",
              stdin="on-call-at-3am\n")  # fmt: skip
    assert r.stdout.strip() == f"added ops (role control) in {path}"
    users("add", "guest", "--file", str(path), "--password-stdin", stdin="just-looking\n")
    r = users("add", "ops", "--file", str(path), "--password-stdin", stdin="a-new-password\n")
    assert r.stdout.strip() == f"new password for ops (role control) in {path}"
    assert users("list", "--file", str(path)).stdout.splitlines() == ["guest view", "ops control"]
    r = users("role", "guest", "control", "--file", str(path))
    assert (r.returncode, r.stdout.strip()) == (0, f"guest has the role control in {path}")
    r = users("role", "ops", "view", "--file", str(path))
    assert {n: u.role for n, u in read_user_lines(path).items()} == {
        "guest": "control",
        "ops": "view",
    }
    assert PasswordHasher().verify(read_users(path)["ops"], "a-new-password"), "hash kept"


def test_a_users_file_from_before_roles_keeps_working_and_its_users_may_act(tmp_path: Path):
    path = tmp_path / "users"
    hashed = PasswordHasher().hash("written-long-ago")
    path.write_text(f"alice:{hashed}\n")
    path.chmod(0o600)
    assert users("list", "--file", str(path)).stdout.splitlines() == ["alice control"]
    users("add", "bob", "--file", str(path), "--password-stdin", stdin="the-new-one-here\n")
    assert read_user_lines(path)["alice"] == User(hashed, "control"), "rewritten, role kept"
    assert f"alice:control:{hashed}\n" in path.read_text()


def test_an_unknown_role_or_user_is_refused_naming_it(tmp_path: Path):
    path = tmp_path / "users"
    users("add", "ann", "--file", str(path), "--password-stdin", stdin="long enough\n")
    r = users("role", "ann", "admin", "--file", str(path))
    assert r.returncode == 2
    assert "'admin' is not one of 'view', 'control'" in r.stderr.splitlines()[-1]
    r = users("role", "zed", "view", "--file", str(path))
    assert (r.returncode, r.stderr.strip()) == (1, f"no user 'zed' in {path}")
