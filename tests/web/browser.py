"""The browser side of the dashboard tests: headless Debian Chromium driven by Playwright, run
*inside* the test's loopback-only namespace (``python -m tests.web.browser SCENARIO ARGS.json``).

A scenario does what a person would on the page, waits on what the page shows (never a fixed
sleep), and writes what it saw to ``<out>/result.json`` (plus screenshots) for the test to
judge. It never downloads a browser: Playwright starts /usr/bin/chromium.
"""

from __future__ import annotations

import json
import re
import sys
import time
import traceback
import urllib.error
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import Any

from playwright.sync_api import Browser, Page, expect, sync_playwright

CHROMIUM = "/usr/bin/chromium"
UNACKED = re.compile(r"^(active|returned) unacked$")


def launch(p: Any, trust_spki: str | None = None) -> Browser:
    """Chromium; `trust_spki` (base64 SHA-256 of a certificate's public key) is trusted for
    HTTPS as if its CA were installed: that key only, every other check still made."""
    args = ["--no-sandbox", "--disable-background-networking", "--no-first-run"]
    if trust_spki:
        args.append(f"--ignore-certificate-errors-spki-list={trust_spki}")
    browser: Browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=args)
    return browser


def http(
    url: str, body: dict[str, Any] | None = None, headers: dict[str, str] | None = None
) -> tuple[int, dict[str, Any]]:
    """A plain HTTP request (not the browser's): status and JSON body."""
    data = json.dumps(body).encode() if body is not None else None
    method = "POST" if data is not None else "GET"
    req = urllib.request.Request(url, data=data, headers=headers or {}, method=method)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, json.loads(r.read() or b"{}")
    except urllib.error.HTTPError as err:
        return err.code, json.loads(err.read() or b"{}")


def page_fetch(page: Page, path: str, body: dict[str, Any], headers: dict[str, str]) -> Any:
    """A POST made by the page itself (its cookies, its origin)."""
    return page.evaluate(
        """async ([path, body, headers]) => {
            const r = await fetch(path, {method: "POST", body: JSON.stringify(body),
                headers: {"Content-Type": "application/json", ...headers}});
            return {status: r.status, body: await r.json()};
        }""",
        [path, body, headers],
    )


def rows(page: Page, table: str) -> list[list[str]]:
    out: list[list[str]] = page.evaluate(
        """(label) => Array.from(document.querySelector(`table[aria-label="${label}"] tbody`).rows)
            .map((tr) => Array.from(tr.cells).map((td) => td.textContent.trim()))""",
        table,
    )
    return out


def wait_rows(
    page: Page,
    table: str,
    cond: Callable[[list[list[str]]], bool],
    what: str,
    timeout: float = 40.0,
) -> Any:
    deadline = time.monotonic() + timeout
    while True:
        got = rows(page, table)
        if cond(got):
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}; {table} shows {got}")
        page.wait_for_timeout(200)  # polling the page's own DOM between its 2 Hz updates


def login(page: Page, user: str, password: str) -> None:
    page.get_by_label("User").fill(user)
    page.get_by_label("Password").fill(password)
    page.get_by_role("button", name="Log in").click()


def tour(args: dict[str, Any], out: Path, result: dict[str, Any]) -> None:
    url = args["url"]
    with sync_playwright() as p:
        browser = launch(p)
        page = browser.new_page(viewport={"width": 1600, "height": 1200})
        page.set_default_timeout(30_000)
        requests: list[str] = []
        failed: list[str] = []
        console: list[str] = []
        page.on("request", lambda r: requests.append(r.url))
        page.on("requestfailed", lambda r: failed.append(f"{r.url}: {r.failure}"))
        page_errors: list[str] = []
        page.on("console", lambda m: console.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: page_errors.append(str(e)))
        result["requests"], result["failed_requests"], result["page_errors"] = (
            requests, failed, page_errors,
        )  # fmt: skip

        page.goto(url)
        page.get_by_role("status", name="Connection").filter(has_text="live").wait_for()
        fleet = wait_rows(
            page,
            "Fleet",
            lambda r: {x[0] for x in r if x[2] != "–"} >= set(args["nodes"]) | {"hub"},
            "every node and its health",
        )
        result["fleet"] = fleet
        streams = wait_rows(
            page,
            "Streams",
            lambda r: {x[0] for x in r} >= set(args["streams"]) and all(x[2] != "0" for x in r),
            "every stream with batches",
        )
        result["streams"] = streams

        # Values change: the fast stream's latest values, read twice from the page.
        def values() -> str:
            return next(x[6] for x in rows(page, "Streams") if x[0] == args["fast_stream"])

        first = values()
        page.wait_for_function(
            """([name, first]) => Array.from(
                    document.querySelectorAll('table[aria-label="Streams"] tbody tr')
                ).some((tr) => tr.cells[0].textContent === name
                    && tr.cells[6].textContent !== first)""",
            arg=[args["fast_stream"], first],
        )
        result["values"] = [first, values()]

        # The default plot draws at the stream's pace (100 ms batches: about 10 frames/s).
        page.wait_for_function("() => window.fleetdaq.stats.drawn >= 3")
        t0, d0 = time.monotonic(), page.evaluate("() => window.fleetdaq.stats.drawn")
        page.wait_for_function(f"() => window.fleetdaq.stats.drawn >= {d0 + 30}")
        result["plot_fps"] = 30 / (time.monotonic() - t0)
        result["plot_frames"] = page.evaluate(
            "() => [window.fleetdaq.stats.frames, window.fleetdaq.stats.resyncs]"
        )
        result["plots"] = page.evaluate(
            "() => Array.from(document.querySelectorAll('canvas'))"
            ".map((c) => c.getAttribute('aria-label'))"
        )
        page.screenshot(path=str(out / "dashboard.png"), full_page=False)

        # An alarm appears: a latched one (it stays unacked until acked, whatever the signal
        # does meanwhile), the demo's substrate_hot, raised in the first weld layer.
        name = args["alarm"]
        wait_rows(
            page,
            "Alarms",
            lambda r: any(x[0] == name and UNACKED.match(x[1]) for x in r),
            f"{name} raised",
            timeout=90,
        )
        result["alarm"] = name
        ack = page.get_by_role("button", name=f"Acknowledge {name}", exact=True)
        result["ack_button_disabled_logged_out"] = ack.is_disabled()

        # What the browser logged before the refusals below (each logs a failed resource).
        result["console_errors"] = list(console)

        # Refused without a login: the page's own fetch, no session.
        result["ack_without_login"] = page_fetch(
            page, "/api/alarms", {"action": "ack", "names": [name]}, {}
        )

        # A wrong password is refused, and says so on the page.
        with page.expect_response("**/api/login") as resp:
            login(page, args["user"], "not-the-password")
        result["wrong_password_status"] = resp.value.status
        # The page writes the message after it has read the response: wait for some text.
        alert = page.get_by_role("alert")
        expect(alert).not_to_have_text("", timeout=10_000)
        result["wrong_password_text"] = alert.inner_text()

        # The login the demo printed works; then the user the test added while the hub ran.
        login(page, args["demo_user"], args["demo_password"])
        page.get_by_text(f"Logged in as {args['demo_user']}").wait_for()
        result["demo_login"] = True
        page.get_by_role("button", name="Log out").click()
        page.get_by_role("button", name="Log in").wait_for()
        login(page, args["user"], args["password"])
        page.get_by_text(f"Logged in as {args['user']}").wait_for()

        # A second plot, through the form: the thermocouple's substrate channel.
        page.get_by_label("Plot stream").select_option("am-cell/tc")
        page.get_by_role("group", name="Channels").get_by_label("substrate").check()
        page.get_by_role("button", name="Add plot").click()
        tc_plot = page.locator(".plot").filter(
            has=page.get_by_role("img", name="Plot of am-cell/tc: substrate")
        )
        tc_plot.get_by_text(re.compile(r"^delay \d+ ms$")).wait_for()  # its first frame, drawn
        result["plots_after_adding"] = page.evaluate(
            "() => Array.from(document.querySelectorAll('canvas'))"
            ".map((c) => c.getAttribute('aria-label'))"
        )

        # Logged in, but without this session's CSRF token (the page's own fetch), and with the
        # token but from another origin (a plain request carrying the session cookie).
        result["ack_without_csrf"] = page_fetch(
            page, "/api/alarms", {"action": "ack", "names": [name]}, {}
        )
        csrf = page.evaluate(
            "() => fetch('/api/session').then((r) => r.json()).then((s) => s.csrf)"
        )
        cookie = "; ".join(f"{c['name']}={c['value']}" for c in page.context.cookies())
        result["ack_foreign_origin"] = http(
            url + "api/alarms",
            {"action": "ack", "names": [name]},
            {"Content-Type": "application/json", "Cookie": cookie, "X-CSRF-Token": csrf,
             "Origin": "http://evil.example"},
        )  # fmt: skip
        result["cookie_flags"] = [
            {k: c.get(k) for k in ("name", "httpOnly", "sameSite")} for c in page.context.cookies()
        ]

        # The ack, through the page: the button, the dialog with a note, the answer.
        ack.click()
        dialog = page.get_by_role("dialog")
        dialog.get_by_label("Note").fill("seen from the dashboard test")
        dialog.get_by_role("button", name="Acknowledge").click()
        toast = page.get_by_role("status").filter(has_text=f"ack {name}:")
        toast.wait_for()
        result["ack_toast"] = toast.inner_text()
        acked = wait_rows(
            page,
            "Alarms",
            lambda r: any(x[0] == name and not UNACKED.match(x[1]) for x in r),
            f"{name} acked",
        )
        result["alarm_after_ack"] = next(x for x in acked if x[0] == name)

        # A split from the page starts a new file.
        def facts() -> dict[str, str]:
            got: dict[str, str] = page.evaluate(
                """() => { const dl = document.getElementById("recorder-facts"); const o = {};
                    for (let i = 0; i < dl.children.length; i += 2)
                        o[dl.children[i].textContent] = dl.children[i + 1].textContent;
                    return o; }"""
            )
            return got

        before = facts()
        page.get_by_role("button", name="Split", exact=True).click()
        page.get_by_role("dialog").get_by_role("button", name="Split").click()
        toast = page.get_by_role("status").filter(has_text="recorder split:")
        toast.wait_for()
        result["split_toast"] = toast.inner_text()
        page.wait_for_function(
            """(n) => document.getElementById("files-count").textContent !== n""",
            arg=before["Files written"],
        )
        after = facts()
        result["recorder_before"], result["recorder_after"] = before, after
        page.screenshot(path=str(out / "after-actions.png"), full_page=True)
        page.get_by_role("status").filter(has_text="recorder split:").wait_for(state="hidden")
        page.screenshot(path=str(out / "docs.png"))  # the README's picture

        page.get_by_role("button", name="Log out").click()
        page.get_by_role("button", name="Log in").wait_for()
        result["split_disabled_after_logout"] = page.get_by_role(
            "button", name="Split", exact=True
        ).is_disabled()

        # A view-role login: it sees everything; every action button stays disabled, and the
        # page's own fetch of an action is refused.
        login(page, args["viewer"], args["viewer_password"])
        page.get_by_text(f"Logged in as {args['viewer']}").wait_for()
        split = page.get_by_role("button", name="Split", exact=True)
        csrf = page.evaluate(
            "() => fetch('/api/session').then((r) => r.json()).then((s) => s.csrf)"
        )
        result["viewer"] = {
            "view_only_shown": page.get_by_text("(view only)").is_visible(),
            "split_disabled": split.is_disabled(),
            "split_title": split.get_attribute("title"),
            "action_buttons": page.evaluate(
                "() => Array.from(document.querySelectorAll('button.needs-login'))"
                ".map((b) => b.disabled)"
            ),
            "split_by_fetch": page_fetch(
                page, "/api/recorder", {"action": "split"}, {"X-CSRF-Token": csrf}
            ),
        }
        page.screenshot(path=str(out / "view-role.png"), full_page=True)
        page.get_by_role("button", name="Log out").click()
        page.get_by_role("button", name="Log in").wait_for()
        result["stats"] = page.evaluate("() => window.fleetdaq.stats.frames")
        result["console_errors_after"] = [
            m for m in console if not m.startswith("Failed to load resource: the server")
        ]
        browser.close()


def outputs(args: dict[str, Any], out: Path, result: dict[str, Any]) -> None:
    """Set an output from the page, with its confirmation, and read the edge's answer."""
    url, output, value = args["url"], args["output"], args["value"]
    with sync_playwright() as p:
        browser = launch(p, args.get("trust_spki"))
        page = browser.new_page(viewport={"width": 1600, "height": 1200})
        page.set_default_timeout(30_000)
        sockets: list[str] = []
        page.on("websocket", lambda ws: sockets.append(ws.url))
        result["websockets"] = sockets
        page.goto(url)
        page.get_by_role("status", name="Connection").filter(has_text="live").wait_for()
        wait_rows(page, "Outputs", lambda r: any(x[0] == output for x in r), f"output {output}")
        login(page, args["user"], args["password"])
        page.get_by_text(f"Logged in as {args['user']}").wait_for()
        page.get_by_role("button", name=f"Set {output}", exact=True).click()
        dialog = page.get_by_role("dialog")
        dialog.get_by_label(re.compile("^Value")).fill(str(value))
        dialog.get_by_label("Reason").fill("dashboard test")
        dialog.get_by_role("button", name="Set output").click()
        toast = page.get_by_role("status").filter(has_text=f"set {output}:")
        toast.wait_for()
        result["toast"] = toast.inner_text()
        result["row"] = wait_rows(
            page,
            "Outputs",
            lambda r: any(x[0] == output and x[2].startswith(f"{value:g}") for x in r),
            f"the readback of {output} at {value}",
        )
        result["cookies"] = [
            {k: c.get(k) for k in ("name", "secure", "httpOnly")} for c in page.context.cookies()
        ]
        wait_rows(
            page,
            "Fleet",
            lambda r: {x[0] for x in r if x[12].endswith(" d")} >= {"rig", "hub"},
            "the certificates' days",
        )
        page.wait_for_function(  # amber once the hub's certificate_expiring/rig is active
            """() => Array.from(document.querySelector('table[aria-label="Fleet"] tbody').rows)
                .some((tr) => tr.cells[0].textContent === "rig"
                              && tr.cells[12].className.includes("warn"))"""
        )
        result["certificates"] = page.evaluate(
            """() => Array.from(document.querySelector('table[aria-label="Fleet"] tbody').rows)
                .map((tr) => [tr.cells[0].textContent, tr.cells[12].textContent,
                              tr.cells[12].className, tr.cells[12].title])"""
        )
        page.screenshot(path=str(out / "outputs.png"), full_page=True)
        browser.close()


def recorder_facts(page: Page) -> dict[str, str]:
    got: dict[str, str] = page.evaluate(
        """() => { const dl = document.getElementById("recorder-facts"); const o = {};
            for (let i = 0; i < dl.children.length; i += 2)
                o[dl.children[i].textContent] = dl.children[i + 1].textContent;
            return o; }"""
    )
    return got


def partitions(args: dict[str, Any], out: Path, result: dict[str, Any]) -> None:
    """A partitioned site: the Recorder panel shows the partition hub's recorder, and a stop
    from the page stops it too (its answer in the toast)."""
    url, part = args["url"], f"Partition {args['partition']}"
    with sync_playwright() as p:
        browser = launch(p)
        page = browser.new_page(viewport={"width": 1600, "height": 1200})
        page.set_default_timeout(30_000)
        page.goto(url)
        page.get_by_role("status", name="Connection").filter(has_text="live").wait_for()
        shows = """([k, state]) => Array.from(document.querySelectorAll("#recorder-facts dt"))
            .some((dt) => dt.textContent === k && dt.nextSibling.textContent.startsWith(state))"""
        page.wait_for_function(shows, arg=[part, "recording"])
        result["before"] = recorder_facts(page)
        hub = f"hub/{args['partition']}"  # the partition hub's own machine, beside the nodes
        result["fleet"] = wait_rows(
            page, "Fleet", lambda r: any(x[0] == hub and x[2] != "–" for x in r), f"{hub}'s health"
        )
        login(page, args["user"], args["password"])
        page.get_by_text(f"Logged in as {args['user']}").wait_for()
        page.get_by_role("button", name="Stop", exact=True).click()
        dialog = page.get_by_role("dialog")
        result["dialog"] = dialog.inner_text()
        dialog.get_by_role("button", name="Stop").click()
        toast = page.get_by_role("status").filter(has_text="recorder stop:")
        toast.wait_for()
        result["toast"] = toast.inner_text()
        page.wait_for_function(shows, arg=[part, "stopped"])
        result["after"] = recorder_facts(page)
        result["after_class"] = page.evaluate(
            """(k) => Array.from(document.querySelectorAll("#recorder-facts dt"))
                .find((dt) => dt.textContent === k).nextSibling.className""",
            part,
        )
        page.screenshot(path=str(out / "partitions.png"), full_page=True)
        browser.close()


SCENARIOS = {"tour": tour, "outputs": outputs, "partitions": partitions}


def main() -> None:
    scenario, args_path = sys.argv[1], Path(sys.argv[2])
    args = json.loads(args_path.read_text())
    out = Path(args["out"])
    out.mkdir(parents=True, exist_ok=True)
    result: dict[str, Any] = {"ok": False}
    try:
        SCENARIOS[scenario](args, out, result)
        result["ok"] = True
    except Exception:
        result["error"] = traceback.format_exc()
    finally:
        (out / "result.json").write_text(json.dumps(result, indent=2, default=str))
    sys.exit(0 if result["ok"] else 1)


if __name__ == "__main__":
    main()
