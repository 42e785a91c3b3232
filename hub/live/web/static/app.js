// fleetdaq dashboard: plain JavaScript, no framework, nothing fetched from anywhere but this hub.
// The hub pushes its state over one WebSocket (/api/live); actions are POSTs with the session's
// CSRF token. Plots are min/max per pixel column, decimated on the hub, drawn on <canvas>.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const S = {
    site: "", user: null, role: null, csrf: null, openView: true, usersDefined: false,
    view: null, streams: {}, outputs: [], events: [], ws: null, retry: 500,
    plots: new Map(), nextPlot: 1, autoPlot: true,
  };
  // What the page measured, for operators (shown) and for tests and benchmarks (read).
  const stats = { states: 0, frames: 0, drawn: 0, delays: [], dropped_by_hub: 0, resyncs: 0 };
  window.fleetdaq = { stats };

  // --- formatting ------------------------------------------------------------------------------
  const SEVERITY = { critical: 0, major: 1, minor: 2, info: 3 };
  const UNACKED = new Set(["active_unacked", "returned_unacked"]);
  const COLORS = ["#6cb6ff", "#f0a35e", "#4cc38a", "#d98bff", "#ffd866", "#ff7a90", "#5ee0d8", "#b0b8c0"];

  function num(v, digits = 4) {
    if (v === null || v === undefined || Number.isNaN(v)) return "–";
    if (v === 0) return "0";
    const a = Math.abs(v);
    if (a >= 1e6 || a < 1e-3) return v.toExponential(2);
    return String(Number(v.toPrecision(digits)));
  }
  function bytes(n) {
    if (n === null || n === undefined) return "–";
    const u = ["B", "kB", "MB", "GB", "TB"];
    let i = 0;
    while (n >= 1000 && i < u.length - 1) { n /= 1000; i++; }
    return `${i ? n.toFixed(n < 10 ? 1 : 0) : n} ${u[i]}`;
  }
  function duration(s) {
    if (s === null || s === undefined || Number.isNaN(s)) return "–";
    if (s < 1) return `${Math.round(s * 1000)} ms`;
    if (s < 90) return `${s.toFixed(s < 10 ? 1 : 0)} s`;
    if (s < 5400) return `${Math.round(s / 60)} min`;
    if (s < 172800) return `${(s / 3600).toFixed(1)} h`;
    return `${(s / 86400).toFixed(1)} d`;
  }
  function offset(ns) {
    if (ns === null || ns === undefined) return "–";
    const a = Math.abs(ns);
    if (a < 1e3) return `${ns} ns`;
    if (a < 1e6) return `${(ns / 1e3).toFixed(1)} µs`;
    if (a < 1e9) return `${(ns / 1e6).toFixed(2)} ms`;
    return `${(ns / 1e9).toFixed(3)} s`;
  }
  function clock(ns) {
    if (!ns) return "–";
    return new Date(ns / 1e6).toISOString().slice(11, 19);
  }
  function el(tag, props = {}, ...children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(props)) {
      if (k === "class") e.className = v;
      else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
      else if (k in e && k !== "list") e[k] = v;
      else e.setAttribute(k, v);
    }
    for (const c of children) e.append(c);
    return e;
  }
  function setText(node, text, cls) {
    if (node.textContent !== text) node.textContent = text;
    if (cls !== undefined && node.className !== cls) node.className = cls;
  }
  function nowNs() { return (performance.timeOrigin + performance.now()) * 1e6; }

  // Keep table rows by key: only changed cells are touched, so buttons keep focus and identity.
  function syncRows(tbody, items, keyOf, create, update) {
    const old = new Map();
    for (const tr of Array.from(tbody.rows)) old.set(tr.dataset.key, tr);
    let prev = null;
    for (const item of items) {
      const key = keyOf(item);
      let tr = old.get(key);
      if (tr) old.delete(key);
      else { tr = create(item); tr.dataset.key = key; }
      update(tr, item);
      const want = prev ? prev.nextSibling : tbody.firstChild;
      if (tr !== want) tbody.insertBefore(tr, want);
      prev = tr;
    }
    for (const tr of old.values()) tr.remove();
  }
  function cells(n, cls = []) {
    const tr = document.createElement("tr");
    for (let i = 0; i < n; i++) tr.append(el("td", { class: cls[i] || "" }));
    return tr;
  }

  let toastTimer = 0;
  function toast(text, bad = false) {
    const t = $("toast");
    t.textContent = text;
    t.className = `toast show${bad ? " bad" : ""}`;
    clearTimeout(toastTimer);
    toastTimer = setTimeout(() => { t.className = "toast"; }, bad ? 8000 : 4000);
  }

  // --- asking before acting --------------------------------------------------------------------
  function ask(title, text, fields = [], confirmLabel = "Confirm") {
    const dlg = $("confirm");
    $("confirm-title").textContent = title;
    $("confirm-text").textContent = text;
    $("confirm-ok").textContent = confirmLabel;
    const box = $("confirm-fields");
    box.replaceChildren();
    const inputs = {};
    for (const f of fields) {
      const input = el("input", { name: f.name, type: f.type || "text", value: f.value ?? "" });
      for (const a of ["min", "max", "step", "required", "maxLength"]) if (f[a] !== undefined) input[a] = f[a];
      inputs[f.name] = input;
      box.append(el("label", {}, `${f.label} `, input));
    }
    return new Promise((resolve) => {
      dlg.returnValue = "";
      dlg.addEventListener("close", () => {
        if (dlg.returnValue !== "ok") { resolve(null); return; }
        const out = {};
        for (const [k, input] of Object.entries(inputs)) out[k] = input.value;
        resolve(out);
      }, { once: true });
      dlg.showModal();
      (fields.length ? inputs[fields[0].name] : $("confirm-ok")).focus();
    });
  }

  // --- talking to the hub ----------------------------------------------------------------------
  async function post(path, body) {
    const r = await fetch(path, {
      method: "POST",
      headers: { "Content-Type": "application/json", "X-CSRF-Token": S.csrf || "" },
      body: JSON.stringify(body),
    });
    let data = {};
    try { data = await r.json(); } catch (e) { data = { ok: false, error: `HTTP ${r.status}` }; }
    if (r.status === 401 && path !== "/api/login") { S.user = null; S.role = null; S.csrf = null; applySession(); }
    return { status: r.status, data };
  }

  async function act(path, body, what) {
    const { data } = await post(path, body);
    let detail = data.error || "";
    if (!detail && data.results) {
      detail = data.results.map((r) => `${r.name}: ${r.done ? r.state : r.reason}`).join("; ");
    }
    if (!detail && data.reply) {
      const r = data.reply;
      detail = r.applied ? `applied, readback ${num(r.readback)}` : `refused: ${r.refusal}: ${r.message}`;
    }
    if (!detail && data.result) detail = data.result;
    for (const [name, a] of Object.entries(data.partition_results || {})) {
      detail += `; partition ${name}: ${a.result || a.error}`;
    }
    toast(`${what}: ${data.ok ? "done" : "refused"}${detail ? ` — ${detail}` : ""}`, !data.ok);
    return data;
  }

  // A view-role login looks; only control acts (the hub refuses anything else with 403).
  const mayAct = () => Boolean(S.user) && S.role === "control";

  async function loadSession() {
    const r = await fetch("/api/session");
    const s = await r.json();
    S.site = s.site; S.user = s.user; S.role = s.role; S.csrf = s.csrf; S.openView = s.open_view;
    S.usersDefined = s.users_defined;
    $("site-name").textContent = `· ${s.site}`;
    document.title = `fleetdaq · ${s.site}`;
    applySession();
  }

  function applySession() {
    const inUser = Boolean(S.user);
    $("login-form").hidden = inUser;
    $("logged-in").hidden = !inUser;
    $("who").textContent = S.user || "";
    $("view-only").hidden = !inUser || mayAct();
    const locked = !S.openView && !inUser;
    $("locked").hidden = !locked;
    $("main").hidden = locked;
    if (!inUser && !S.usersDefined) {
      $("login-error").textContent = "no users yet: run `fleetdaq users add NAME` on the hub";
    }
    for (const b of document.querySelectorAll(".needs-login")) {
      b.disabled = !mayAct();
      b.title = mayAct() ? "" : inUser ? "your role is view: acting needs control" : "log in to act";
    }
    if (S.view) render();
  }

  $("login-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const { status, data } = await post("/api/login", {
      user: $("login-user").value, password: $("login-password").value,
    });
    $("login-password").value = "";
    if (data.ok) {
      S.user = data.user; S.role = data.role; S.csrf = data.csrf;
      $("login-error").textContent = "";
      applySession();
      reconnect();
    } else {
      $("login-error").textContent = status === 429 ? `${data.error}` : data.error || "login refused";
    }
  });
  $("logout").addEventListener("click", async () => {
    await post("/api/logout", {});
    S.user = null; S.role = null; S.csrf = null;
    applySession();
    reconnect();
  });

  // --- the live connection ---------------------------------------------------------------------
  function connect() {
    if (!S.openView && !S.user) return;
    const ws = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/api/live`);
    S.ws = ws;
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { S.retry = 500; setConn("live", "ok"); sendPlots(); };
    ws.onmessage = (m) => {
      if (m.data instanceof ArrayBuffer) { onFrame(decodeFrame(m.data)); return; }
      const msg = JSON.parse(m.data);
      if (msg.type === "state") onState(msg);
      else if (msg.type === "events") onEvents(msg.events);
      else if (msg.type === "error") toast(`live view: ${msg.error}`, true);
    };
    ws.onclose = (ev) => {
      if (S.ws !== ws) return;
      S.ws = null;
      if (ev.code === 4001) { // the session ended: show the login, connect again after it
        S.user = null; S.role = null; S.csrf = null;
        setConn("logged out", "warn");
        applySession();
        return;
      }
      setConn(ev.code === 1001 ? "hub stopped — reconnecting…" : "reconnecting…", ev.code === 1001 ? "bad" : "warn");
      setTimeout(connect, S.retry);
      S.retry = Math.min(S.retry * 2, 10000);
    };
  }
  function reconnect() {
    const old = S.ws;
    S.ws = null;
    if (old) old.close();
    connect();
  }
  function setConn(text, level) {
    setText($("connection"), text, `pill pill-${level}`);
  }
  function sendPlots() {
    if (!S.ws || S.ws.readyState !== WebSocket.OPEN) return;
    const plots = Array.from(S.plots.values()).map((p) => { p.awaitFull = true; return p.request(); });
    S.ws.send(JSON.stringify({ type: "plots", plots }));
  }

  function onState(msg) {
    stats.states++;
    S.view = msg.view;
    S.streams = msg.streams || {};
    S.outputs = msg.outputs || [];
    stats.dropped_by_hub = msg.dashboard ? msg.dashboard.ws_dropped : 0;
    stats.hub = msg.dashboard || null;
    render();
  }

  function onEvents(events) {
    const seen = S.events.length ? S.events[S.events.length - 1].seq : 0;
    for (const e of events) if (e.seq > seen) S.events.push(e);
    if (S.events.length > 2000) S.events.splice(0, S.events.length - 2000);
    renderEvents();
  }

  // A frame: uint32 header length, the JSON header, then per channel the minima and the maxima
  // of columns first_col..newest_col as float32 (NaN: no sample in that column). Whole when
  // base_col is null, else a delta on the frame whose newest column was base_col. See
  // hub/web/frames.py (its Assembler does in Python what Plot.apply does here).
  function decodeFrame(buf) {
    const n = new DataView(buf).getUint32(0, true);
    const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 4, n)));
    const values = new Float32Array(buf, 4 + n);
    const c = head.newest_col - head.first_col + 1;
    head.channels = head.channels.map((ch, i) => ({
      name: ch.name, unit: ch.unit, min: values.subarray(2 * i * c, (2 * i + 1) * c), max: values.subarray((2 * i + 1) * c, (2 * i + 2) * c),
    }));
    return head;
  }

  function onFrame(msg) {
    stats.frames++;
    const d = (nowNs() - msg.latest_ns) / 1e6;
    stats.delays.push(d);
    if (stats.delays.length > 5000) stats.delays.splice(0, 1000);
    const p = S.plots.get(msg.id);
    if (p) p.onFrame(msg, d);
  }

  // --- panels ----------------------------------------------------------------------------------
  function render() {
    const v = S.view;
    if (!v) return;
    renderSummary(v);
    renderAlarms(v);
    renderFleet(v);
    renderStreams(v);
    renderRecorder(v);
    renderOutputs();
    renderRules(v);
    renderPlotForm();
  }

  function renderSummary(v) {
    const inAlarm = v.alarms.filter((a) => a.state !== "normal" && a.state !== "disabled");
    const unacked = v.alarms.filter((a) => UNACKED.has(a.state)).length;
    const alive = v.nodes.filter((n) => n.alive).length;
    const rec = v.recorder;
    const parts = [
      ["Hub time", `${clock(v.time_ns)} UTC`],
      ["Nodes", `${alive}/${v.nodes.length} alive`],
      ["Recorder", rec.state],
      ["Alarms", `${inAlarm.length} in alarm, ${unacked} unacked`],
    ];
    if (v.failures && v.failures.length) parts.push(["Failed", v.failures.map((f) => f[0]).join(", ")]);
    const box = $("summary");
    if (box.childElementCount !== parts.length) {
      box.replaceChildren(...parts.map(() => el("span", {}, el("span"), " ", el("strong"))));
    }
    parts.forEach(([k, val], i) => {
      setText(box.children[i].children[0], k);
      setText(box.children[i].children[1], val);
    });
    box.children[2].children[1].className = rec.state === "recording" ? "ok" : "bad";
    box.children[3].children[1].className = unacked ? "bad" : inAlarm.length ? "warn" : "ok";
  }

  function renderAlarms(v) {
    const all = $("alarms-all").checked;
    const shown = v.alarms
      .filter((a) => all || a.state !== "normal" || a.active)
      .sort((a, b) => (UNACKED.has(b.state) - UNACKED.has(a.state))
        || (SEVERITY[a.severity] - SEVERITY[b.severity]) || a.name.localeCompare(b.name));
    setText($("alarm-count"), `(${v.alarms.length} defined)`);
    $("alarms-empty").hidden = shown.length > 0;
    syncRows($("alarms-body"), shown, (a) => a.name, (a) => {
      const tr = cells(6, ["", "", "", "num", "", ""]);
      const box = el("div", { class: "buttons" },
        el("button", { type: "button", class: "needs-login", "aria-label": `Acknowledge ${a.name}`,
          onclick: () => ackAlarm(tr.dataset.key) }, "Ack"),
        el("button", { type: "button", class: "needs-login", "aria-label": `Shelve ${a.name}`,
          onclick: () => shelveAlarm(tr.dataset.key) }, "Shelve"),
        el("button", { type: "button", class: "needs-login", "aria-label": `Unshelve ${a.name}`,
          onclick: () => unshelveAlarm(tr.dataset.key) }, "Unshelve"));
      tr.cells[5].append(box);
      return tr;
    }, (tr, a) => {
      const c = tr.cells;
      setText(c[0], a.name);
      c[0].title = a.description || a.condition || "";
      let state = a.state.replace("_", " ");
      if (a.state === "shelved") state += ` until ${clock(a.shelved_until_ns)}`;
      setText(c[1], state, UNACKED.has(a.state) ? "bad" : "");
      setText(c[2], a.severity, `sev-${a.severity}`);
      setText(c[3], a.value === null ? "–" : `${num(a.value)} ${a.unit}`.trim(), "num");
      setText(c[4], a.since_ns ? `${clock(a.since_ns)} (${duration((v.time_ns - a.since_ns) / 1e9)} ago)` : "–");
      tr.classList.toggle("unacked", UNACKED.has(a.state));
      const [ack, shelve, unshelve] = c[5].querySelectorAll("button");
      ack.disabled = !mayAct() || !UNACKED.has(a.state);
      shelve.disabled = !mayAct() || a.state === "shelved" || a.state === "disabled";
      unshelve.disabled = !mayAct() || a.state !== "shelved";
    });
  }

  async function ackAlarm(name) {
    const got = await ask(`Acknowledge ${name}?`, "The acknowledgement is recorded with your name.",
      [{ name: "note", label: "Note", maxLength: 500 }], "Acknowledge");
    if (got) await act("/api/alarms", { action: "ack", names: [name], note: got.note }, `ack ${name}`);
  }
  async function shelveAlarm(name) {
    const got = await ask(`Shelve ${name}?`, "A shelved alarm is not annunciated until it is unshelved or the time runs out.",
      [{ name: "minutes", label: "For (minutes)", type: "number", value: "60", min: "1", max: "43200", required: true },
        { name: "note", label: "Why", maxLength: 500, required: true }], "Shelve");
    if (got) {
      await act("/api/alarms", { action: "shelve", names: [name], for_s: Number(got.minutes) * 60, note: got.note },
        `shelve ${name}`);
    }
  }
  async function unshelveAlarm(name) {
    const got = await ask(`Unshelve ${name}?`, "", [{ name: "note", label: "Note", maxLength: 500 }], "Unshelve");
    if (got) await act("/api/alarms", { action: "unshelve", names: [name], note: got.note }, `unshelve ${name}`);
  }
  $("alarms-all").addEventListener("change", render);

  function fleetRows(v) {
    const byNode = new Map(((v.fleet && v.fleet.nodes) || []).map((n) => [n.node, n]));
    const rows = v.nodes.map((n) => ({ name: n.node, alive: n.alive, h: n.health, t: byNode.get(n.node), rx: n.health_received_ns }));
    if (v.hub_health) rows.push({ name: "hub", alive: true, h: v.hub_health, t: byNode.get("hub"), rx: v.hub_health.time_ns });
    // A partitioned site: each partition hub's own machine (hub/<name>), from its health.
    for (const p of v.partition_hubs || []) rows.push({ name: p.node, alive: p.alive, h: p.health, t: byNode.get(p.node), rx: p.health_received_ns });
    return rows;
  }
  function renderFleet(v) {
    const f = v.fleet || {};
    const gms = f.grandmasters || [];
    let line = gms.length ? `Grandmaster: ${gms.join(", ")}` : "No node is locked to a grandmaster";
    if (gms.length) line += f.same_grandmaster ? " — the whole fleet follows one grandmaster" : " — NOT ONE GRANDMASTER";
    if (f.max_abs_offset_ns !== undefined && f.max_abs_offset_ns !== null) line += ` · max |offset| ${offset(f.max_abs_offset_ns)}`;
    setText($("fleet-time"), line, f.same_grandmaster === false ? "note bad" : "note");
    const num13 = ["", "", "", "num", "num", "num", "num", "num", "", "num", "", "num", "num"];
    const alarmed = new Set(v.alarms.filter((a) => a.active).map((a) => a.name));
    syncRows($("fleet-body"), fleetRows(v), (r) => r.name, () => cells(13, num13), (tr, r) => {
      const c = tr.cells;
      const h = r.h;
      const host = h ? h.host : null;
      setText(c[0], r.name);
      const stale = h && v.time_ns - r.rx > 5e9;
      setText(c[1], r.alive ? (stale ? "stale" : "yes") : "NO", r.alive ? (stale ? "warn" : "ok") : "bad");
      setText(c[2], h ? h.version : "–");
      setText(c[3], h ? duration(h.uptime_s) : "–", "num");
      setText(c[4], host ? `${num(host.cpu_percent, 3)} %` : "–", "num");
      const mem = host && host.memory_total_bytes ? 100 * (1 - host.memory_available_bytes / host.memory_total_bytes) : null;
      setText(c[5], mem === null ? "–" : `${mem.toFixed(0)} %`, "num");
      const disks = host ? host.disks.filter((d) => d.total_bytes > 0) : [];
      const worst = disks.length ? Math.min(...disks.map((d) => 100 * d.free_bytes / d.total_bytes)) : null;
      setText(c[6], worst === null ? "–" : `${worst.toFixed(0)} %`, worst !== null && worst < 10 ? "num bad" : "num");
      c[6].title = disks.map((d) => `${d.role}: ${bytes(d.free_bytes)} free of ${bytes(d.total_bytes)}`).join("\n");
      setText(c[7], host && host.cpu_temperature_c !== null ? `${num(host.cpu_temperature_c, 3)} °C` : "–", "num");
      const t = r.t;
      const state = t ? t.state : h && h.clock.known ? h.clock.state : "no source";
      setText(c[8], state, t && t.level === "fail" ? "bad" : t && t.level === "warn" ? "warn" : state === "locked" ? "ok" : "");
      setText(c[9], t ? offset(t.offset_ns) : "–", "num");
      setText(c[10], t && t.grandmaster_id ? t.grandmaster_id : "–");
      const spool = h ? h.streams.reduce((s, x) => s + x.spool_bytes, 0) : null;
      setText(c[11], spool === null ? "–" : bytes(spool), "num");
      certificate(c[12], h, v.time_ns, alarmed.has(`certificate_expiring/${r.name}`));
    });
  }
  // Days until the TLS pair the machine connects with ends (its health says when): red once
  // it has ended, amber while its certificate_expiring alarm is active.
  function certificate(td, h, now, expiring) {
    const ends = h ? h.certificate_not_after_ns : 0;
    if (!ends) {
      setText(td, "–", "num");
      const why = h ? "no TLS, or the node cannot tell" : "";
      if (td.title !== why) td.title = why;
      return;
    }
    const left = (ends - now) / 86400e9;  // rounded as `fleetdaq fleet status` does
    setText(td, left < 0 ? "ended" : `${Math.round(left)} d`, left < 0 ? "num bad" : expiring ? "num warn" : "num");
    const when = `ends ${new Date(ends / 1e6).toISOString().slice(0, 16).replace("T", " ")} UTC`;
    if (td.title !== when) td.title = when;
  }

  function renderStreams(v) {
    const rows = [...v.streams].sort((a, b) => `${a.node}/${a.stream}`.localeCompare(`${b.node}/${b.stream}`));
    syncRows($("streams-body"), rows, (s) => `${s.node}/${s.stream}`, () => cells(7, ["", "num", "num", "num", "num", "num", "values"]), (tr, s) => {
      const c = tr.cells;
      const name = `${s.node}/${s.stream}`;
      setText(c[0], s.recorded ? name : `${name} (not recorded)`);
      const off = s.rate_hz && s.batches > 2 && Math.abs(s.scan_rate - s.rate_hz) > 0.05 * s.rate_hz;
      setText(c[1], `${num(s.scan_rate, 4)} (${num(s.rate_hz, 4)}) /s`, off ? "num warn" : "num");
      setText(c[2], String(s.batches), "num");
      setText(c[3], String(s.gaps), s.gaps ? "num bad" : "num");
      setText(c[4], String(s.lost), s.lost ? "num bad" : "num");
      const age = s.last_receive_ns ? (v.time_ns - s.last_receive_ns) / 1e9 : null;
      setText(c[5], age === null ? "never" : duration(Math.max(0, age)), age === null || age > 5 ? "num bad" : "num");
      const live = S.streams[name];
      const text = live ? live.channels.map((ch, i) => `${ch} ${num(live.latest[i])} ${live.units[i]}`.trim()).join(" · ") : "";
      setText(c[6], text, "values");
    });
  }

  function renderRecorder(v) {
    const r = v.recorder;
    const snap = v.snapshots || {};
    const facts = [
      ["State", r.state],
      ["Session", r.session || "–"],
      ["Current file", r.current_file ? r.current_file.split("/").pop() : "–"],
      ["Current size", bytes(r.current_file_bytes)],
      ["Files written", String(r.files.length)],
      ["Snapshot buffer", snap.enabled ? `${num(snap.covers_s, 3)} s of ${num(snap.seconds, 3)} s held (${bytes(snap.held_bytes)}), ${snap.written} written${snap.last ? `, last ${snap.last.split("/").pop()}` : ""}` : "off"],
    ];
    if (r.write_errors || r.abandoned_files.length) facts.push(["Problems", `${r.write_errors} write errors, ${r.abandoned_files.length} abandoned files`]);
    // A partitioned site: each partition hub's recorder, from its report (start, stop and split
    // reach them all).
    const bad = new Set(r.state === "recording" ? [] : ["State"]);
    for (const [name, p] of Object.entries(v.partitions || {}).sort()) {
      const pr = p.recorder || {};
      const k = `Partition ${name}`;
      if (!p.alive || !pr.state) {
        facts.push([k, p.alive ? "no report yet" : "gone — its nodes spool until it returns"]);
        bad.add(k);
        continue;
      }
      const file = pr.current_file ? ` · ${pr.current_file.split("/").pop()} ${bytes(pr.current_file_bytes || 0)}` : "";
      const dk = p.data_disk || {};
      const disk = dk.total_bytes ? ` · disk ${num(100 * dk.free_bytes / dk.total_bytes, 2)} % free` : "";
      facts.push([k, `${pr.state} · ${pr.session || "–"}${file}${disk}`]);
      if (pr.state !== "recording") bad.add(k);
    }
    const dl = $("recorder-facts");
    if (dl.childElementCount !== facts.length * 2) dl.replaceChildren(...facts.flatMap(() => [el("dt"), el("dd")]));
    facts.forEach(([k, val], i) => {
      setText(dl.children[2 * i], k);
      const mark = k === "State" || k.startsWith("Partition ") ? (bad.has(k) ? "bad" : "ok") : "";
      setText(dl.children[2 * i + 1], val, mark);
    });
    setText($("files-count"), String(r.files.length));
    const list = $("files-list");
    if (list.childElementCount !== r.files.length) {
      list.replaceChildren(...r.files.slice().reverse().map((f) => el("li", {}, f.split("/").pop())));
    }
  }
  for (const b of document.querySelectorAll("[data-rec]")) {
    b.addEventListener("click", async () => {
      const action = b.dataset.rec;
      const texts = {
        start: "Start a new recording session.",
        stop: "Stop recording: nothing is written until it is started again.",
        split: "Close the current file and go on in a new one.",
        snapshot: "Write the snapshot buffer (the last seconds of everything) to a file.",
      };
      const every = Object.keys((S.view && S.view.partitions) || {}).length ? " On every hub of the site." : "";
      const got = await ask(`${b.textContent} recording?`, texts[action] + every,
        action === "snapshot" ? [{ name: "note", label: "Note", maxLength: 500 }] : [], b.textContent);
      if (got) await act("/api/recorder", { action, ...(got.note ? { note: got.note } : {}) }, `recorder ${action}`);
    });
  }

  function renderOutputs() {
    $("outputs-empty").hidden = S.outputs.length > 0;
    syncRows($("outputs-body"), S.outputs, (o) => o.output, (o) => {
      const tr = cells(6, ["", "num", "num", "", "", ""]);
      const input = el("input", { type: "number", step: "any", size: 6, "aria-label": `Value for ${o.output}` });
      const b = (label, fn) => el("button", { type: "button", class: "needs-login", "aria-label": `${label} ${o.output}`, onclick: () => fn(tr.dataset.key, input.value) }, label);
      tr.cells[5].append(el("div", { class: "buttons" }, input, b("Set", setOutput), b("Pulse", pulseOutput), b("Arm", (n) => armOutput(n, "arm")), b("Disarm", (n) => armOutput(n, "disarm"))));
      return tr;
    }, (tr, o) => {
      const c = tr.cells;
      const st = o.state;
      const unit = (o.config && o.config.unit) || (st && st.unit) || "";
      setText(c[0], o.alive ? o.output : `${o.output} (node down)`, o.alive ? "" : "bad");
      c[0].title = (o.config && o.config.description) || "";
      setText(c[1], st ? `${num(st.value)} ${unit}`.trim() : "–", "num");
      setText(c[2], st ? `${num(st.readback)} ${unit}`.trim() : "–", "num");
      setText(c[3], st ? (st.safe_state ? "safe state" : st.armed ? "armed" : "not armed") : "–", st && st.safe_state ? "warn" : "");
      const locks = [...(st ? st.interlocks : []), ...(o.interlock ? [`hub: ${o.interlock}`] : [])];
      setText(c[4], locks.join(", ") || "none", locks.length ? "warn" : "");
      for (const btn of c[5].querySelectorAll("button")) btn.disabled = !mayAct() || !o.alive;
    });
  }
  function outputUnit(name) {
    const o = S.outputs.find((x) => x.output === name);
    return (o && o.config && o.config.unit) || "";
  }
  async function setOutput(name, value) {
    const got = await ask(`Set ${name}?`, `The output is driven on its node; the edge checks limits, arming and interlocks.`,
      [{ name: "value", label: `Value (${outputUnit(name) || "no unit"})`, type: "number", value, step: "any", required: true },
        { name: "reason", label: "Reason", maxLength: 500 }], "Set output");
    if (got) await act("/api/outputs", { action: "set", output: name, value: Number(got.value), reason: got.reason }, `set ${name}`);
  }
  async function pulseOutput(name, value) {
    const got = await ask(`Pulse ${name}?`, "Set the value for the given time, then back.",
      [{ name: "value", label: `Value (${outputUnit(name) || "no unit"})`, type: "number", value, step: "any", required: true },
        { name: "seconds", label: "For (seconds)", type: "number", value: "1", min: "0.001", max: "3600", step: "any", required: true },
        { name: "reason", label: "Reason", maxLength: 500 }], "Pulse output");
    if (got) {
      await act("/api/outputs", { action: "pulse", output: name, value: Number(got.value), pulse_s: Number(got.seconds), reason: got.reason },
        `pulse ${name}`);
    }
  }
  async function armOutput(name, action) {
    const got = await ask(`${action === "arm" ? "Arm" : "Disarm"} ${name}?`, "", [{ name: "reason", label: "Reason", maxLength: 500 }],
      action === "arm" ? "Arm" : "Disarm");
    if (got) await act("/api/outputs", { action, output: name, reason: got.reason }, `${action} ${name}`);
  }

  function renderRules(v) {
    const rules = (v.rules && v.rules.rules) || [];
    const locks = (v.rules && v.rules.interlocks) || [];
    syncRows($("rules-body"), rules, (r) => r.name, () => cells(4, ["", "", "num", ""]), (tr, r) => {
      setText(tr.cells[0], r.name);
      tr.cells[0].title = r.description || "";
      setText(tr.cells[1], r.state);
      setText(tr.cells[2], String(r.fired), "num");
      setText(tr.cells[3], r.last_result || "–");
    });
    syncRows($("interlocks-body"), locks, (i) => i.name, () => cells(4, ["", "", "num", ""]), (tr, i) => {
      setText(tr.cells[0], i.name);
      setText(tr.cells[1], i.active ? "ACTIVE" : "no", i.active ? "bad" : "ok");
      setText(tr.cells[2], String(i.trips), "num");
      setText(tr.cells[3], i.outputs.join(", "));
    });
  }

  function renderEvents() {
    const level = Number($("ev-level").value);
    const node = $("ev-node").value;
    const source = $("ev-source").value.trim();
    const text = $("ev-text").value.trim().toLowerCase();
    const nodes = new Set(S.events.map((e) => e.node));
    const sel = $("ev-node");
    for (const n of nodes) {
      if (!Array.from(sel.options).some((o) => o.value === n)) sel.append(el("option", { value: n }, n));
    }
    const shown = [];
    for (let i = S.events.length - 1; i >= 0 && shown.length < 300; i--) {
      const e = S.events[i];
      if (e.level < level || (node && e.node !== node) || (source && e.source !== source)) continue;
      if (text && !e.message.toLowerCase().includes(text) && !e.tag.toLowerCase().includes(text)) continue;
      shown.push(e);
    }
    syncRows($("events-body"), shown, (e) => String(e.seq), (e) => {
      const tr = cells(5, ["", "", "", "", "msg"]);
      tr.className = `level-${e.level_name}`;
      const when = new Date(e.time_ns / 1e6).toISOString().slice(11, 23);
      [when, e.level_name, e.node, e.source, e.tag ? `[${e.tag}] ${e.message}` : e.message]
        .forEach((t, i) => { tr.cells[i].textContent = t; });
      return tr;
    }, () => {});
  }
  for (const id of ["ev-level", "ev-node", "ev-source", "ev-text"]) $(id).addEventListener("input", renderEvents);
  $("event-filters").addEventListener("submit", (ev) => ev.preventDefault());

  // --- live plots ------------------------------------------------------------------------------
  class Plot {
    constructor(stream, channels, span) {
      this.id = `p${S.nextPlot++}`;
      this.stream = stream;
      this.channels = channels;
      this.span = span;
      this.frame = null;
      this.cols = null;
      this.newest = null;
      this.awaitFull = true;
      this.pending = false;
      this.canvas = el("canvas", { role: "img", "aria-label": `Plot of ${stream}: ${channels.join(", ")}` });
      this.delay = el("span", { class: "muted" });
      this.legend = el("span", { class: "legend" });
      const remove = el("button", { type: "button", "aria-label": `Remove plot of ${stream}`, onclick: () => this.remove() }, "×");
      this.root = el("div", { class: "plot" },
        el("header", {}, el("strong", {}, `${stream} · ${span} s`), this.legend, this.delay, remove), this.canvas);
      $("plots").append(this.root);
      this.width = this.pixelWidth();
    }
    pixelWidth() {
      return Math.max(50, Math.min(4000, Math.round(this.canvas.clientWidth * (window.devicePixelRatio || 1)) || 600));
    }
    request() {
      return { id: this.id, stream: this.stream, channels: this.channels, width: this.width, span_s: this.span };
    }
    remove() {
      S.plots.delete(this.id);
      this.root.remove();
      savePlots();
      sendPlots();
    }
    // The whole plot, kept from whole frames and deltas; false: a delta this plot cannot take
    // (it missed one, or its width changed): it asks for its plots again, a whole frame follows.
    apply(msg) {
      const W = msg.width;
      if (msg.base_col === null) {
        this.cols = Object.fromEntries(msg.channels.map((ch) => [ch.name, { unit: ch.unit, min: ch.min.slice(), max: ch.max.slice() }]));
        this.awaitFull = false;
      } else {
        if (this.awaitFull) return false;
        const any = this.cols && Object.values(this.cols)[0];
        if (!any || this.newest !== msg.base_col || any.min.length !== W) {
          stats.resyncs++;
          sendPlots();
          return false;
        }
        const shift = msg.newest_col - this.newest;
        const at = msg.first_col - (msg.newest_col - W + 1);
        for (const ch of msg.channels) {
          const c = this.cols[ch.name];
          for (const a of [c.min, c.max]) {
            if (shift > 0) { a.copyWithin(0, shift); a.fill(NaN, Math.max(0, W - shift)); }
          }
          c.min.set(ch.min, at);
          c.max.set(ch.max, at);
        }
      }
      this.newest = msg.newest_col;
      this.frame = { width: W, start_ns: msg.start_ns, end_ns: msg.end_ns, latest_ns: msg.latest_ns, channels: this.cols };
      return true;
    }
    onFrame(msg, delayMs) {
      if (!this.apply(msg)) return;
      this.lastDelay = delayMs;
      if (!this.pending) {
        this.pending = true;
        requestAnimationFrame(() => { this.pending = false; this.draw(); });
      }
    }
    draw() {
      const f = this.frame;
      if (!f) return;
      stats.drawn++;
      const cv = this.canvas;
      const dpr = window.devicePixelRatio || 1;
      const W = f.width;
      const H = Math.round(cv.clientHeight * dpr) || 190;
      if (cv.width !== W || cv.height !== H) { cv.width = W; cv.height = H; }
      const ctx = cv.getContext("2d");
      ctx.clearRect(0, 0, W, H);
      const names = Object.keys(f.channels);
      let lo = Infinity;
      let hi = -Infinity;
      for (const n of names) {
        const ch = f.channels[n];
        for (let x = 0; x < W; x++) {
          if (ch.min[x] < lo) lo = ch.min[x]; // NaN compares false: skipped
          if (ch.max[x] > hi) hi = ch.max[x];
        }
      }
      if (!Number.isFinite(lo)) { lo = -1; hi = 1; }
      if (hi - lo < 1e-12) { lo -= 1; hi += 1; }
      const pad = (hi - lo) * 0.06;
      lo -= pad; hi += pad;
      const top = 4 * dpr;
      const bottom = H - 14 * dpr;
      const Y = (val) => bottom - ((val - lo) / (hi - lo)) * (bottom - top);
      ctx.font = `${11 * dpr}px system-ui, sans-serif`;
      ctx.fillStyle = "#8794a1";
      ctx.strokeStyle = "#26303a";
      ctx.lineWidth = 1;
      for (let i = 0; i <= 4; i++) {
        let val = lo + ((hi - lo) * i) / 4;
        if (Math.abs(val) < (hi - lo) * 1e-6) val = 0;
        const y = Math.round(Y(val)) + 0.5;
        ctx.beginPath(); ctx.moveTo(0, y); ctx.lineTo(W, y); ctx.stroke();
        ctx.fillText(num(val, 3), 3 * dpr, i === 4 ? y + 11 * dpr : y - 2 * dpr);
      }
      ctx.fillText(`−${this.span} s`, 3 * dpr, H - 3 * dpr);
      const endText = `${clock(f.end_ns)} UTC`;
      ctx.fillText(endText, W - ctx.measureText(endText).width - 3 * dpr, H - 3 * dpr);
      // A stream slower than a pixel column (a 4 Hz thermocouple over 10 s) leaves empty columns
      // between its samples: those are joined by a line; a longer hole is a real gap.
      const live = S.streams[this.stream];
      const nsPerColumn = (f.end_ns - f.start_ns) / W;
      const join = live ? Math.max(2, Math.ceil((2 * live.bucket_ns) / nsPerColumn)) : 2;
      names.forEach((n, k) => {
        const ch = f.channels[n];
        const color = COLORS[k % COLORS.length];
        ctx.fillStyle = color;
        ctx.strokeStyle = color;
        ctx.lineWidth = dpr;
        let pmin = null;
        let pmax = null;
        let lastX = -Infinity;
        let lastMid = 0;
        for (let x = 0; x < W; x++) {
          let a = ch.min[x];
          let b = ch.max[x];
          if (Number.isNaN(a) || Number.isNaN(b)) { pmin = pmax = null; continue; }
          const na = a;
          const nb = b;
          if (pmax !== null && pmax < a) a = pmax; // rising: join the previous column
          if (pmin !== null && pmin > b) b = pmin; // falling
          const y1 = Y(b);
          const y2 = Y(a);
          ctx.fillRect(x, y1, 1, Math.max(dpr, y2 - y1));
          const mid = Y((na + nb) / 2);
          if (x - lastX > 1 && x - lastX <= join) {
            ctx.beginPath(); ctx.moveTo(lastX + 0.5, lastMid); ctx.lineTo(x + 0.5, mid); ctx.stroke();
          }
          lastX = x; lastMid = mid;
          pmin = na; pmax = nb;
        }
      });
      if (this.legend.childElementCount !== names.length) {
        this.legend.replaceChildren(...names.map((n, k) => {
          const swatch = el("i");
          swatch.style.background = COLORS[k % COLORS.length];
          return el("span", {}, swatch, el("span"));
        }));
      }
      names.forEach((n, k) => {
        const i = live ? live.channels.indexOf(n) : -1;
        const val = i >= 0 ? `${num(live.latest[i])} ${live.units[i]}`.trim() : f.channels[n].unit;
        setText(this.legend.children[k].children[1], `${n} ${val}`);
      });
      setText(this.delay, `delay ${Math.round(this.lastDelay)} ms`);
    }
  }

  function savePlots() {
    const list = Array.from(S.plots.values()).map((p) => ({ stream: p.stream, channels: p.channels, span: p.span }));
    try { localStorage.setItem(`fleetdaq.plots.${S.site}`, JSON.stringify(list)); } catch (e) { /* private mode */ }
  }
  function addPlot(stream, channels, span) {
    const p = new Plot(stream, channels, span);
    S.plots.set(p.id, p);
    savePlots();
    sendPlots();
  }
  function restorePlots() {
    let list = null;
    try { list = JSON.parse(localStorage.getItem(`fleetdaq.plots.${S.site}`) || "null"); } catch (e) { list = null; }
    if (!Array.isArray(list)) return false;
    for (const p of list) {
      if (S.streams[p.stream] && Array.isArray(p.channels)) addPlot(p.stream, p.channels.filter((c) => S.streams[p.stream].channels.includes(c)), p.span);
    }
    return true;
  }

  let formStreams = "";
  function renderPlotForm() {
    const names = Object.keys(S.streams).sort();
    const key = names.join("|");
    if (key !== formStreams) {
      formStreams = key;
      const sel = $("plot-stream");
      const keep = sel.value;
      sel.replaceChildren(...names.map((n) => el("option", { value: n }, n)));
      if (names.includes(keep)) sel.value = keep;
      renderChannelChoices();
    }
    if (S.autoPlot && names.length) {
      S.autoPlot = false;
      if (!restorePlots()) {
        // First visit: the fastest stream's first two channels.
        const fastest = names.reduce((a, b) => (S.streams[b].bucket_ns < S.streams[a].bucket_ns ? b : a));
        addPlot(fastest, S.streams[fastest].channels.slice(0, 2), 10);
      }
    }
  }
  function renderChannelChoices() {
    const box = $("plot-channels");
    const stream = S.streams[$("plot-stream").value];
    box.replaceChildren(el("legend", {}, "Channels"));
    if (!stream) return;
    stream.channels.forEach((ch, i) => {
      box.append(el("label", {}, el("input", { type: "checkbox", name: "channel", value: ch, checked: i === 0 }), ` ${ch}`));
    });
  }
  $("plot-stream").addEventListener("change", renderChannelChoices);
  $("plot-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const stream = $("plot-stream").value;
    const channels = Array.from($("plot-channels").querySelectorAll("input:checked")).map((i) => i.value);
    if (!stream || !channels.length) { toast("choose a stream and at least one channel", true); return; }
    addPlot(stream, channels, Number($("plot-span").value));
  });
  let resizeTimer = 0;
  window.addEventListener("resize", () => {
    clearTimeout(resizeTimer);
    resizeTimer = setTimeout(() => {
      let changed = false;
      for (const p of S.plots.values()) {
        const w = p.pixelWidth();
        if (w !== p.width) { p.width = w; changed = true; }
      }
      if (changed) sendPlots();
    }, 250);
  });

  // --- start -----------------------------------------------------------------------------------
  loadSession().then(connect).catch((err) => {
    setConn("hub unreachable", "bad");
    toast(`cannot reach the hub: ${err}`, true);
    setTimeout(() => loadSession().then(connect), 3000);
  });
})();
