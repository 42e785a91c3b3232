"""The SMTP password: from the environment or an owner-only file, refused clearly otherwise,
and never shown."""

from __future__ import annotations

import base64
import os
from pathlib import Path

import pytest

from fleetdaq.hub.config.notify import SmtpConfig
from fleetdaq.hub.errors import SecretError
from fleetdaq.hub.supervision.notify.credentials import Secret, read_password


def smtp(**kw: object) -> SmtpConfig:
    return SmtpConfig.model_validate(
        {"host": "mail.example.com", "sender": "hub@x.example", "username": "hub", **kw}
    )


def password_file(tmp_path: Path, mode: int, text: str = "s3cret pw\n") -> Path:
    path = tmp_path / "smtp-password"
    path.write_text(text, encoding="utf-8")
    path.chmod(mode)
    return path


def test_the_password_comes_from_a_file_only_its_owner_may_read(tmp_path: Path) -> None:
    path = password_file(tmp_path, 0o600)
    secret = read_password(smtp(password_file=str(path)))
    assert secret is not None
    assert secret.reveal() == "s3cret pw"


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660])
def test_a_password_file_others_may_read_is_refused_in_one_line(tmp_path: Path, mode: int) -> None:
    path = password_file(tmp_path, mode)
    with pytest.raises(SecretError) as err:
        read_password(smtp(password_file=str(path)))
    message = str(err.value)
    assert "\n" not in message
    assert str(path) in message
    assert f"mode {mode:04o}" in message
    assert f"chmod 600 {path}" in message
    assert "s3cret" not in message


@pytest.mark.parametrize(
    ("content", "problem"),
    [(None, "no such file"), ("", "the first line is empty"), ("\nx\n", "the first line is")],
)
def test_a_missing_or_empty_password_file_is_refused(
    tmp_path: Path, content: str | None, problem: str
) -> None:
    path = tmp_path / "pw"
    if content is not None:
        password_file(tmp_path, 0o600, content).rename(path)
    with pytest.raises(SecretError, match=problem):
        read_password(smtp(password_file=str(path)))


def test_a_directory_is_not_a_password_file(tmp_path: Path) -> None:
    (tmp_path / "d").mkdir(mode=0o700)
    with pytest.raises(SecretError, match="not a regular file"):
        read_password(smtp(password_file=str(tmp_path / "d")))


def test_the_password_comes_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("FLEETDAQ_TEST_SMTP_PW", "from-env")
    secret = read_password(smtp(password_env="FLEETDAQ_TEST_SMTP_PW"))
    assert secret is not None
    assert secret.reveal() == "from-env"


def test_an_unset_environment_variable_is_refused_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FLEETDAQ_TEST_SMTP_PW", raising=False)
    with pytest.raises(SecretError, match=r"FLEETDAQ_TEST_SMTP_PW .* is not set"):
        read_password(smtp(password_env="FLEETDAQ_TEST_SMTP_PW"))


def test_no_username_means_no_password() -> None:
    plain = SmtpConfig.model_validate({"host": "relay", "sender": "a@b.example"})
    assert read_password(plain) is None


def test_a_secret_never_prints_itself_and_redacts_every_form_of_it() -> None:
    s = Secret("hunter2!", "hub")
    assert "hunter2" not in repr(s)
    assert "hunter2" not in str(s)
    assert "hunter2" not in f"{s}"
    on_the_wire = [
        "hunter2!",
        base64.b64encode(b"hunter2!").decode(),  # AUTH LOGIN
        base64.b64encode(b"\0hub\0hunter2!").decode(),  # AUTH PLAIN
    ]
    for form in on_the_wire:
        assert form not in s.redact(f"server said: {form} was wrong")


def test_a_read_only_file_of_its_owner_is_accepted(tmp_path: Path) -> None:
    path = password_file(tmp_path, 0o400)
    assert os.stat(path).st_mode & 0o077 == 0
    secret = read_password(smtp(password_file=str(path)))
    assert secret is not None
