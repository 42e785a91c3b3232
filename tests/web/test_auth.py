"""Logins, sessions, rate limits and the CSRF/Origin checks, on their own (time from a clock the
test moves, so nothing waits)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from fleetdaq.hub.live.web.auth import Auth, RateLimiter, csrf_ok, origin_problem
from fleetdaq.hub.live.web.users import (
    User,
    UsersFile,
    UsersFileError,
    parse_users,
    read_user_lines,
    read_users,
    write_users,
)
from tests.web.conftest import CHEAP, write_cheap_users


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock() -> Clock:
    return Clock()


@pytest.fixture
def auth(tmp_path: Path, clock: Clock) -> Auth:
    path = tmp_path / "users"
    write_cheap_users(path, {"alice": "correct horse", "bob": "battery staple"})
    return Auth(UsersFile(path), session_ttl_s=600, clock=clock, max_failures=3, window_s=60)


def test_the_right_password_opens_a_session_and_a_wrong_one_does_not(auth: Auth):
    ok = auth.login("alice", "correct horse", "10.0.0.5")
    assert ok.session is not None
    assert ok.session.user == "alice"
    assert auth.session(ok.session.token) is ok.session
    wrong = auth.login("alice", "battery staple", "10.0.0.5")
    assert wrong.session is None
    assert wrong.error == "wrong user name or password"


def test_an_unknown_user_is_refused_exactly_like_a_wrong_password(auth: Auth):
    unknown = auth.login("mallory", "correct horse", "10.0.0.5")
    wrong = auth.login("alice", "nope", "10.0.0.5")
    assert unknown.session is None
    assert unknown.error == wrong.error


def test_a_session_expires_after_its_ttl_without_use(auth: Auth, clock: Clock):
    s = auth.login("alice", "correct horse", "10.0.0.5").session
    assert s is not None
    clock.now += 601
    assert auth.session(s.token) is None
    assert auth.session(s.token) is None, "gone for good"


def test_using_a_session_renews_it(auth: Auth, clock: Clock):
    s = auth.login("alice", "correct horse", "10.0.0.5").session
    assert s is not None
    for _ in range(5):
        clock.now += 500
        assert auth.session(s.token) is s
    assert clock.now - s.created > 600, "lived past one ttl because it was used"


def test_logout_ends_the_session(auth: Auth):
    s = auth.login("bob", "battery staple", "10.0.0.5").session
    assert s is not None
    auth.logout(s.token)
    assert auth.session(s.token) is None


def test_removing_a_user_or_changing_their_password_ends_their_sessions(auth: Auth, tmp_path: Path):
    a = auth.login("alice", "correct horse", "10.0.0.5").session
    b = auth.login("bob", "battery staple", "10.0.0.5").session
    assert a is not None
    assert b is not None
    path = tmp_path / "users"
    write_users(path, {"bob": CHEAP.hash("a new password")})
    assert auth.session(a.token) is None, "alice was removed"
    assert auth.session(b.token) is None, "bob's password changed"
    assert auth.login("bob", "a new password", "10.0.0.5").session is not None


def test_repeated_failures_lock_out_the_user_for_the_window(auth: Auth, clock: Clock):
    for _ in range(3):
        assert auth.login("alice", "guess", "10.0.0.5").retry_after_s == 0
    locked = auth.login("alice", "correct horse", "10.0.0.6")
    assert locked.session is None
    assert locked.retry_after_s == pytest.approx(60)
    assert auth.login("bob", "battery staple", "10.0.0.6").session is not None, "others may"
    clock.now += 61
    assert auth.login("alice", "correct horse", "10.0.0.6").session is not None


def test_an_address_guessing_many_users_is_locked_out(auth: Auth):
    for i in range(12):  # 4 x max_failures, each user only once
        assert auth.login(f"user{i}", "guess", "10.9.9.9").retry_after_s == 0
    assert auth.login("alice", "correct horse", "10.9.9.9").retry_after_s > 0
    assert auth.login("alice", "correct horse", "10.0.0.1").session is not None
    assert auth.rate_limited == 1


def test_the_rate_limiter_keeps_a_bounded_number_of_keys(clock: Clock):
    limiter = RateLimiter(max_failures=2, window_s=60, max_keys=100, clock=clock)
    for i in range(10_000):
        limiter.failed(f"name{i}")
    assert len(limiter._keys) == 100
    limiter.failed("name9999")
    assert limiter.retry_after("name9999") > 0, "the newest keys are the ones kept"


def test_the_csrf_token_must_be_the_sessions_own(auth: Auth):
    a = auth.login("alice", "correct horse", "10.0.0.5").session
    b = auth.login("bob", "battery staple", "10.0.0.5").session
    assert a is not None
    assert b is not None
    assert csrf_ok(a, a.csrf)
    assert not csrf_ok(a, b.csrf)
    assert not csrf_ok(a, None)
    assert not csrf_ok(a, "")


@pytest.mark.parametrize(
    ("origin", "referer", "host", "refused"),
    [
        ("http://127.0.0.1:8080", None, "127.0.0.1:8080", False),
        ("http://hub.site:8080", None, "hub.site:8080", False),
        ("http://evil.example", None, "127.0.0.1:8080", True),
        ("http://127.0.0.1:9999", None, "127.0.0.1:8080", True),
        ("https://127.0.0.1:8080", None, "127.0.0.1:8080", False),  # a TLS proxy in front
        ("http://127.0.0.1:8080.evil.example", None, "127.0.0.1:8080", True),
        ("null", None, "127.0.0.1:8080", True),
        (None, "http://127.0.0.1:8080/page", "127.0.0.1:8080", False),
        (None, "http://evil.example/x", "127.0.0.1:8080", True),
        (None, None, "127.0.0.1:8080", True),
        ("http://127.0.0.1:8080", None, None, True),
    ],
)
def test_a_state_changing_request_must_come_from_the_dashboards_own_page(
    origin: str | None, referer: str | None, host: str | None, refused: bool
):
    why = origin_problem(origin, referer, host)
    assert bool(why) is refused, why


def test_the_users_file_is_written_0600_and_read_back(tmp_path: Path):
    path = tmp_path / "sub" / "users"
    write_users(path, {"alice": CHEAP.hash("x" * 10), "bob": CHEAP.hash("y" * 10)})
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert sorted(read_users(path)) == ["alice", "bob"]
    assert [p.name for p in path.parent.iterdir()] == ["users"], "no temporary file left"


def test_a_users_file_line_that_is_not_name_and_hash_is_named_and_left_out(tmp_path: Path):
    users, problems = parse_users(
        "# comment\n\nalice:control:$argon2id$x\nbob plain\n:$argon2id$y\n"
        "carol:admin:$argon2id$z\n",
        "f",
    )
    assert users == {"alice": User("$argon2id$x", "control")}
    assert problems == [
        "f:4: not NAME:ROLE:ARGON2-HASH; line ignored",
        "f:5: not NAME:ROLE:ARGON2-HASH; line ignored",
        "f:6: not NAME:ROLE:ARGON2-HASH; line ignored",
    ]
    path = tmp_path / "users"
    path.write_text("bob plain\n")
    with pytest.raises(UsersFileError, match="users:1: not NAME:ROLE:ARGON2-HASH"):
        read_users(path)


def test_a_line_without_a_role_from_before_roles_is_control_and_a_stated_role_counts():
    users, problems = parse_users("alice:$argon2id$x\nbob:view:$argon2id$y\n", "f")
    assert problems == []
    assert users == {"alice": User("$argon2id$x", "control"), "bob": User("$argon2id$y", "view")}


def test_rewriting_the_users_file_keeps_each_users_role_unless_told(tmp_path: Path):
    path = tmp_path / "users"
    write_users(path, {"alice": "$argon2id$a", "bob": "$argon2id$b"}, {"alice": "view"})
    write_users(path, {"alice": "$argon2id$a2", "bob": "$argon2id$b", "demo": "$argon2id$d"})
    assert read_user_lines(path) == {
        "alice": User("$argon2id$a2", "view"),
        "bob": User("$argon2id$b", "control"),
        "demo": User("$argon2id$d", "control"),
    }
    assert "alice:view:$argon2id$a2\n" in path.read_text(), "every line says its role"


def test_a_sessions_role_follows_the_users_file_at_its_next_use(tmp_path: Path, clock: Clock):
    path = tmp_path / "users"
    write_cheap_users(path, {"vera": "vera-password"}, {"vera": "view"})
    auth = Auth(UsersFile(path), session_ttl_s=600, clock=clock)
    s = auth.login("vera", "vera-password", "10.0.0.5").session
    assert s is not None
    assert (s.role, s.may_act) == ("view", False)
    write_users(path, read_users(path), {"vera": "control"})
    again = auth.session(s.token)
    assert again is not None, "a new role does not end the session"
    assert (again.role, again.may_act) == ("control", True)


def test_a_login_says_whether_the_name_typed_is_a_users(auth: Auth):
    assert auth.login("alice", "nope", "10.0.0.5").known_user is True
    assert auth.login("hunter2-typed-here", "x", "10.0.0.5").known_user is False
    assert auth.login("alice", "correct horse", "10.0.0.5").known_user is True


def test_the_hub_reads_the_users_file_again_when_it_changes(tmp_path: Path):
    path = tmp_path / "users"
    users = UsersFile(path)
    assert users.names() == []
    write_users(path, {"alice": CHEAP.hash("x" * 10)})
    assert users.names() == ["alice"]
    reloads = users.reloads
    assert users.names() == ["alice"]
    assert users.reloads == reloads, "not read again while unchanged"
    os.unlink(path)
    assert users.names() == [], "no file: nobody can log in"
