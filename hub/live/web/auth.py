"""Who may act on the dashboard: logins checked against the users file (argon2), refused for a
while after repeated failures, server-side sessions that expire unless used, and the checks
every state-changing request passes (a CSRF token tied to the session, and an Origin that is
the page's own).

Nothing here touches the network or an event loop: the web layer calls it (the password check,
which costs ~0.15 s of CPU by design, on a worker thread). Time comes from `clock` (monotonic
seconds), so tests need not wait.
"""

from __future__ import annotations

import hmac
import secrets
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from urllib.parse import urlsplit

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError, VerifyMismatchError

from fleetdaq.contract.config.security import Role
from fleetdaq.hub.live.web.users import UNSTATED_ROLE, UsersFile

COOKIE = "fleetdaq_session"
CSRF_HEADER = "X-CSRF-Token"
MAX_PASSWORD = 1024


@dataclass(slots=True)
class Session:
    token: str
    user: str
    csrf: str
    hashed: str
    """The user's hash at login: a changed password (or a removed user) ends the session."""
    expires: float
    created: float
    role: Role = UNSTATED_ROLE
    """As the users file says at the session's last use: a new role counts at the next click."""

    @property
    def may_act(self) -> bool:
        return self.role == "control"


@dataclass(frozen=True, slots=True)
class LoginResult:
    session: Session | None
    error: str = ""
    retry_after_s: float = 0.0
    """More than 0: refused because of earlier failures, try again after this many seconds."""
    known_user: bool = False
    """The name typed is a user's: only then may it be recorded (an unknown one may be a
    password typed into the wrong field)."""


@dataclass(slots=True)
class _Failures:
    times: deque[float] = field(default_factory=deque)


class RateLimiter:
    """Refuses a key (a user name, a client address) that failed `max_failures` times within
    `window_s`, until the oldest of those failures is `window_s` old. Keeps at most `max_keys`
    keys (the least recently failed go first), so a flood of names cannot grow memory."""

    def __init__(
        self,
        max_failures: int = 5,
        window_s: float = 300.0,
        max_keys: int = 10_000,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.max_failures = max_failures
        self.window_s = window_s
        self.max_keys = max_keys
        self.clock = clock
        self._keys: OrderedDict[str, _Failures] = OrderedDict()
        self._lock = threading.Lock()

    def _recent(self, key: str, now: float) -> deque[float] | None:
        entry = self._keys.get(key)
        if entry is None:
            return None
        while entry.times and entry.times[0] <= now - self.window_s:
            entry.times.popleft()
        if not entry.times:
            del self._keys[key]
            return None
        return entry.times

    def retry_after(self, key: str) -> float:
        """Seconds until `key` may try again; 0 when it may now."""
        now = self.clock()
        with self._lock:
            times = self._recent(key, now)
            if times is None or len(times) < self.max_failures:
                return 0.0
            return max(0.0, times[-self.max_failures] + self.window_s - now)

    def failed(self, key: str) -> None:
        now = self.clock()
        with self._lock:
            entry = self._keys.pop(key, None) or _Failures()
            entry.times.append(now)
            while len(entry.times) > self.max_failures:
                entry.times.popleft()
            self._keys[key] = entry
            while len(self._keys) > self.max_keys:
                self._keys.popitem(last=False)

    def succeeded(self, key: str) -> None:
        with self._lock:
            self._keys.pop(key, None)


class Auth:
    """Logins, sessions and the checks of state-changing requests."""

    def __init__(
        self,
        users: UsersFile,
        session_ttl_s: float,
        clock: Callable[[], float] = time.monotonic,
        max_failures: int = 5,
        window_s: float = 300.0,
        max_sessions: int = 1000,
        hasher: PasswordHasher | None = None,
    ) -> None:
        self.users = users
        self.ttl_s = session_ttl_s
        self.clock = clock
        self.max_sessions = max_sessions
        self.hasher = hasher or PasswordHasher()
        self.per_user = RateLimiter(max_failures, window_s, clock=clock)
        self.per_address = RateLimiter(max_failures * 4, window_s, clock=clock)
        """An address may try a few users (a shared control-room PC), not hundreds."""
        self._sessions: OrderedDict[str, Session] = OrderedDict()
        self._lock = threading.Lock()
        self._dummy: str | None = None
        self.logins = 0
        self.failures = 0
        self.rate_limited = 0

    # --- logging in ---------------------------------------------------------------------------

    def login(self, user: str, password: str, address: str) -> LoginResult:
        """Check a password (blocking: ~0.15 s of CPU; call it off the event loop)."""
        hashed = self.users.hash_of(user) if len(user) <= 64 else None
        known = hashed is not None
        wait = max(self.per_user.retry_after(user), self.per_address.retry_after(address))
        if wait > 0:
            self.rate_limited += 1
            return LoginResult(None, "too many failed logins; try again later", wait, known)
        ok = False
        if len(password) <= MAX_PASSWORD:
            try:
                # An unknown user costs the same as a wrong password: timing says nothing.
                ok = self.hasher.verify(hashed or self._dummy_hash(), password)
            except (VerifyMismatchError, VerificationError, InvalidHashError):
                ok = False
        if not ok or hashed is None:
            self.failures += 1
            self.per_user.failed(user)
            self.per_address.failed(address)
            return LoginResult(None, "wrong user name or password", known_user=known)
        self.per_user.succeeded(user)
        self.logins += 1
        return LoginResult(self._new_session(user, hashed), known_user=True)

    def _dummy_hash(self) -> str:
        if self._dummy is None:
            self._dummy = self.hasher.hash(secrets.token_urlsafe(16))
        return self._dummy

    def _new_session(self, user: str, hashed: str) -> Session:
        now = self.clock()
        s = Session(
            token=secrets.token_urlsafe(32),
            user=user,
            csrf=secrets.token_urlsafe(32),
            hashed=hashed,
            expires=now + self.ttl_s,
            created=now,
            role=self.users.role_of(user) or UNSTATED_ROLE,
        )
        with self._lock:
            self._sessions[s.token] = s
            while len(self._sessions) > self.max_sessions:
                self._sessions.popitem(last=False)
        return s

    # --- sessions -----------------------------------------------------------------------------

    def session(self, token: str | None) -> Session | None:
        """The live session of a cookie's token, renewed by this use; None when there is none,
        it expired, or its user was removed or given a new password since."""
        if not token:
            return None
        now = self.clock()
        with self._lock:
            s = self._sessions.get(token)
            if s is None:
                return None
            if s.expires <= now:
                del self._sessions[token]
                return None
        user = self.users.user(s.user)
        if user is None or user.hashed != s.hashed:
            with self._lock:
                self._sessions.pop(token, None)
            return None
        with self._lock:
            s.role = user.role
            s.expires = now + self.ttl_s
            self._sessions.move_to_end(token)
        return s

    def valid(self, token: str | None) -> bool:
        """Whether a session is live, without renewing it (a page left open is not a use)."""
        now = self.clock()
        with self._lock:
            s = self._sessions.get(token or "")
        return s is not None and s.expires > now and self.users.hash_of(s.user) == s.hashed

    def logout(self, token: str | None) -> None:
        if token:
            with self._lock:
                self._sessions.pop(token, None)

    def active_sessions(self) -> int:
        now = self.clock()
        with self._lock:
            for token in [t for t, s in self._sessions.items() if s.expires <= now]:
                del self._sessions[token]
            return len(self._sessions)


def csrf_ok(session: Session, token: str | None) -> bool:
    """The request carries this session's own CSRF token (compared in constant time)."""
    return bool(token) and hmac.compare_digest(session.csrf.encode(), (token or "").encode())


def origin_problem(origin: str | None, referer: str | None, host: str | None) -> str:
    """Why a state-changing request does not come from the dashboard's own page ('' when it
    does): its Origin (or, without one, its Referer) must name this server as the browser
    addressed it (the Host header). The scheme is not compared, so a TLS proxy in front that
    passes the Host header through works."""
    if not host:
        return "the request has no Host header"
    own = host.lower()
    if origin == "null":
        return "the request comes from an opaque origin"
    seen_from = origin if origin is not None else referer
    if not seen_from:
        return "the request has neither an Origin nor a Referer header"
    seen = urlsplit(seen_from).netloc.lower()
    what = "origin" if origin is not None else "referer"
    return "" if seen == own else f"{what} {seen_from} is not this dashboard ({own})"
