// imubench station page: renders the station's state (server-sent events from /api/events)
// one column per device; the page that owns a device drives it, any other page watches.
// Who this page is: the station prints its address with a one-time secret (#token=..., a
// fragment no server ever receives); the page trades it for a session (POST /api/session),
// keeps that in sessionStorage (this scheme, host and port only: no page of another local
// server can read it) and sends it in X-Imubench-Session with every request. No cookie: a
// browser would send 127.0.0.1's cookies to every port. Pictures come as data: URLs and a
// report through a single-use ticket, since an <img> or a new tab cannot carry the header.
"use strict";
(function () {
  const cols = {};                 // device key -> column element
  const cardStates = {};           // key/name -> last state seen (for the transition log)
  window.__transitions = [];
  window.__streamErrors = 0;       // event stream failures (a healthy session has none)       // [key, pose name, state] as the page saw them (tests read it)
  let last = null;

  const $ = (sel, el) => (el || document).querySelector(sel);
  const esc = (s) => String(s == null ? "" : s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" }[c]));
  const fmt = (x, d) => (x == null || !isFinite(x) ? "–" : Number(x).toFixed(d));

  const SESSION_KEY = "imubench-station-session";
  let session = sessionStorage.getItem(SESSION_KEY);
  const withSession = (h) => Object.assign({ "X-Imubench-Session": session || "" }, h || {});

  async function post(path, body) {
    const r = await fetch(path, { method: "POST", headers: withSession({ "Content-Type": "application/json" }),
      body: JSON.stringify(body), credentials: "omit", cache: "no-store" });
    const j = await r.json().catch(() => ({}));
    if (!r.ok) throw new Error(j.error || r.statusText);
    return j;
  }

  async function getJSON(path) {
    const r = await fetch(path, { headers: withSession(), credentials: "omit", cache: "no-store" });
    const j = await r.json().catch(() => ({}));
    if (!r.ok) throw new Error(j.error || r.statusText);
    return j;
  }

  // the secret in the address, traded once for this tab's session (a reload keeps the session)
  async function openSession() {
    const m = /^#(?:.*&)?token=([A-Za-z0-9_-]{1,100})/.exec(location.hash);
    if (m) {
      history.replaceState(null, "", location.pathname + location.search);   // out of the address bar at once
      const r = await fetch("/api/session", { method: "POST", credentials: "omit", cache: "no-store",
        headers: { "Content-Type": "application/json", "X-Imubench-Launch": m[1] }, body: "{}" });
      const j = await r.json().catch(() => ({}));
      if (!r.ok) { if (!session) throw new Error(j.error || r.statusText); return; }
      session = j.session;
      sessionStorage.setItem(SESSION_KEY, session);
    }
    if (!session) throw new Error("open the address the station printed in its terminal: the secret in it opens this page");
  }

  // pictures drawn by the station: fetched with the session, shown as data: URLs (cached)
  const pictures = new Map();
  function loadPictures(root) {
    for (const img of (root || document).querySelectorAll("img[data-src]")) {
      const url = img.dataset.src;
      if (img.dataset.shown === url) continue;
      img.dataset.shown = url;
      if (!pictures.has(url)) {
        pictures.set(url, fetch(url, { headers: withSession(), credentials: "omit" })
          .then((r) => (r.ok ? r.text() : Promise.reject(new Error(r.statusText))))
          .then((svg) => "data:image/svg+xml;charset=utf-8," + encodeURIComponent(svg))
          .catch((e) => { pictures.delete(url); throw e; }));
      }
      pictures.get(url).then((src) => { if (img.dataset.src === url) img.src = src; }).catch(() => { img.dataset.shown = ""; });
    }
  }

  // a report opens in a new tab through a single-use ticket (a tab sends no header)
  document.addEventListener("click", async (ev) => {
    const a = ev.target.closest && ev.target.closest("a.report-link");
    if (!a) return;
    ev.preventDefault();
    const tab = window.open("about:blank", "_blank");
    try {
      const j = await post("/api/ticket", { path: a.dataset.report });
      if (tab) { tab.opener = null; tab.location = j.url; } else window.location.assign(j.url);
    } catch (e) { if (tab) tab.close(); a.title = e.message; }
  });

  // an export file downloads through a single-use ticket too (a download sends no header)
  document.addEventListener("click", async (ev) => {
    const a = ev.target.closest && ev.target.closest("a.export-link");
    if (!a || !a.dataset.export) return;
    ev.preventDefault();
    try {
      const j = await post("/api/ticket", { path: a.dataset.export });
      const dl = document.createElement("a");
      dl.href = j.url; dl.download = a.getAttribute("download") || ""; dl.rel = "noopener";
      document.body.appendChild(dl); dl.click(); dl.remove();
    } catch (e) { a.title = e.message; }
  });

  async function claim(key) {
    const j = await post("/api/claim", { key: key });
    return !!j.yours;
  }

  // ------------------------------------------------------------------ events
  // server-sent events read with fetch (an EventSource cannot send the session header)
  let stream = null;
  let gone = false;                     // the event stream broke: the station (its server) may be gone
  async function reconnect() {
    if (stream) stream.abort();
    const ctl = stream = new AbortController();
    let wait = 1000;
    try {
      const r = await fetch("/api/events", { headers: withSession(), credentials: "omit", cache: "no-store",
        signal: ctl.signal });
      if (!r.ok) { wait = 3000; const j = await r.json().catch(() => ({})); throw new Error(j.error || r.statusText); }
      $("#conn").textContent = "live";
      if (gone) { gone = false; if (last) render(last); }
      const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
      let buf = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += value;
        let i;
        while ((i = buf.indexOf("\n\n")) >= 0) {
          const data = buf.slice(0, i).split("\n").filter((l) => l.startsWith("data: ")).map((l) => l.slice(6)).join("\n");
          buf = buf.slice(i + 2);
          if (data) { last = JSON.parse(data); render(last); }
        }
      }
    } catch (e) {
      if (ctl.signal.aborted) return;
      $("#conn").textContent = "reconnecting… " + (e.message || "");
    }
    if (ctl !== stream) return;
    window.__streamErrors += 1;
    if ($("#conn").textContent === "live") $("#conn").textContent = "reconnecting…";
    // the station is gone (Ctrl-C, closed): nothing runs any more as far as this page can know
    if (!gone) { gone = true; if (last) render(last); }
    setTimeout(() => { if (ctl === stream) reconnect(); }, wait);
  }

  const claiming = {};
  let claimChain = Promise.resolve();   // one claim at a time
  function render(snap) {
    const mine = snap.boards.filter((b) => b.yours);
    $("#boards").classList.toggle("multi", snap.boards.length > 1);
    for (const b of snap.boards) {
      // a session started by the command is owned by the first page that opens
      if (!b.owned && !claiming[b.key] && (snap.mode === "session" || b.status === "running")) {
        claiming[b.key] = true;
        claimChain = claimChain.then(() => claim(b.key)).catch(() => false).finally(() => { claiming[b.key] = false; });
      }
      renderBoard(b);
    }
    renderOverview(snap);
    loadPictures();
    const watching = snap.boards.filter((b) => b.owned && !b.yours);
    // the boards this page drives or is claiming (a session's claims go one at a time): the
    // full list from the first second, not as the claims come back
    const driving = snap.boards.filter((b) => b.yours || (!b.owned && claiming[b.key]));
    const slots = driving.every((b) => b.device && b.device.slot) && driving.length > 1;
    $("#role").textContent = driving.length ? "you drive " + (slots ? "slots " + ranges(driving.map((b) => b.device.slot))
      : driving.map((b) => b.key).join(", "))
      : watching.length ? "read-only: watching" : "";
    $("#role").className = "pill " + (mine.length ? "done" : watching.length ? "readonly" : "");
    const busy = mine.some((b) => b.status === "running");
    $("#setup").hidden = !(snap.mode === "idle" && !busy);
    $("#use-sim").parentElement.hidden = !snap.sim;
  }

  function ranges(nums) {               // [1,2,3,5,7,8] -> "1–3, 5, 7–8"
    const n = [...nums].sort((a, b) => a - b), out = [];
    for (let i = 0; i < n.length; i++) {
      let j = i;
      while (j + 1 < n.length && n[j + 1] === n[j] + 1) j++;
      out.push(j > i ? `${n[i]}–${n[j]}` : `${n[i]}`);
      i = j;
    }
    return out.join(", ");
  }

  // ------------------------------------------------------------------ a station session's overview
  // every board at a glance (slot, device, stage, progress, verdict), the plate once; a board's
  // full column on demand (click its tile)
  let selected = null;
  const tiles = {};
  const STAGES = { waiting: "waiting", connect: "connecting", health: "health check", rest: "rest: noise and gyro bias",
    poses: "attitudes", turntable: "turntable turns", fit: "fit", write: "write-back", verify: "verification",
    record: "recording", done: "done", sensor: "capture", link: "link" };

  function overall(b) {
    const F = b.fixture || {};
    if (F.state === "passed") return 1;
    const done = b.plan.filter((c) => c.state === "done").length;
    const adaptive = b.config && b.config.capture === "adaptive" && b.method === "multi";
    const need = adaptive ? Math.max(12, done + (b.targets && b.targets.reached ? 0 : 1)) : (b.plan.length || 1);
    const m = /^\[(\d+)\/(\d+)\]/.exec(F.message || "");
    return { connect: 0.02, health: 0.04, rest: 0.07, poses: 0.1 + 0.6 * Math.min(1, done / need), turntable: 0.7,
      fit: 0.72, write: 0.76, verify: 0.8 + 0.2 * (m ? (m[1] - 1) / m[2] : 0), record: 1, done: 1 }[F.stage] || 0;
  }

  function renderOverview(snap) {
    const fixture = snap.boards.length > 1 && snap.boards.every((b) => b.device && b.device.slot);
    $("#overview").hidden = !fixture;
    $("#boards").classList.toggle("overview-on", fixture);
    if (!fixture) return;
    const P = snap.plate || {}, O = snap.over;
    const closed = !!(P.closed || O) || gone;
    const M = closed ? null : P.move;
    const kindWords = { pose: "attitude", verify: "verification attitude", turn: "turn" };
    $("#plate").classList.toggle("closed", closed);
    $(".plate-now", $("#plate")).innerHTML = M ? `${kindWords[M.kind] || M.kind} <b>${esc(M.key)}</b>` +
      (M.words ? ` (${esc(M.words)})` : "") + ` <small>move ${M.move}</small>`
      : O ? "session over: the plate is free" : gone ? "no news: the station is gone" : "not moved yet";
    // the end: the pass count (and why it ended early), once the session is over
    const ov = $("#over");
    ov.hidden = !O && !gone;
    ov.className = "over " + (O ? (O.passed === O.boards ? "passed" : "failed") : "gone");
    ov.textContent = O ? `${O.text}` + (O.failed ? `; ${O.failed} failed` : "")
      : gone ? "the station is gone (stopped, or its command ended): the boards below show their last known state" : "";
    $(".plate-for", $("#plate")).textContent = M ? `for slot${M.serves.length > 1 ? "s" : ""} ${M.serves.join(", ")}` +
      (M.waiting.length ? `; slot${M.waiting.length > 1 ? "s" : ""} ${M.waiting.join(", ")} wait` : "") : "";
    $(".plate-deadlines", $("#plate")).textContent = P.deadlines || "";
    const sorted = [...snap.boards].sort((x, y) => x.device.slot - y.device.slot);
    for (const b of sorted) {
      let t = tiles[b.key];
      if (!t) {
        t = document.createElement("div");
        t.className = "tile";
        t.dataset.key = b.key;
        t.innerHTML = `<div class="top"><span class="slot"></span><span class="uid"></span><span class="state"></span></div>` +
          `<div class="stage"></div><div class="msg"></div><div class="bar"><div class="bar-fill"></div></div><div class="verdict-text"></div>`;
        t.onclick = () => { selected = selected === b.key ? null : b.key; if (last) render(last);
          if (selected && cols[selected]) cols[selected].scrollIntoView({ block: "start" }); };
        $("#tiles").appendChild(t);
        tiles[b.key] = t;
      }
      const F = b.fixture || {};
      let state = b.result ? ({ pass: "passed", stopped: "stopped" }[b.result.status] || "failed")
        : F.state === "passed" || F.state === "stopped" ? F.state
        : F.state === "failed" || b.status === "failed" ? "failed" : b.status === "stopped" ? "stopped" : "running";
      if (gone && state === "running") state = "stopped";        // the station is gone: nothing runs here any more
      const waiting = state === "running" && !!F.waiting;
      t.className = "tile " + state + (waiting ? " waiting" : "") + (selected === b.key ? " selected" : "");
      t.dataset.state = state;
      $(".slot", t).textContent = F.slot || b.device.slot;
      $(".uid", t).textContent = b.device.uid || "(no device ID yet)";
      $(".uid", t).title = (b.device.url || b.key) + (b.device.parts ? "\nparts: " + b.device.parts.join(", ") : "");
      $(".state", t).textContent = state === "running" ? (waiting ? "waits" : "running") : state;
      const done = b.plan.filter((c) => c.state === "done").length;
      let stage = STAGES[F.stage] || F.stage || b.phase || "";
      if (F.stage === "poses" || (done && state === "running" && F.stage !== "verify")) stage += ` · ${done} captured` +
        (b.targets && b.targets.reached ? ", targets reached" : "");
      $(".stage", t).textContent = (state === "running" ? "" : "stopped at ") + stage;
      if (state === "passed") $(".stage", t).textContent = `${done} attitudes, written and verified`;
      $(".msg", t).textContent = state === "running" ? F.message || "" : b.device.url || "";
      $(".bar-fill", t).style.width = fmt(100 * (state === "passed" ? 1 : overall(b)), 0) + "%";
      let v = "";
      if (state === "passed") v = "PASSED" + (b.result ? ": " + b.result.verdict : "");
      else if (state === "failed") v = "FAILED " + (b.result && b.result.verdict ? b.result.verdict
        : F.reason ? `at ${F.stage}: ${F.reason}` : b.error || "");
      else if (state === "stopped") v = "STOPPED " + (b.result && b.result.verdict ? b.result.verdict
        : F.reason ? `at ${F.stage}: ${F.reason}` : gone ? "(the station is gone; its last stage is shown)" : "");
      else if (waiting) v = F.waiting;
      else if (F.stage === "poses" && b.live && b.live.state) {      // what the board sees now
        const L = b.live;
        v = L.state === "moving" ? "moving" : L.attitude ? `now in ${L.attitude}: ${L.state === "still" ? "holding" : L.state}` +
          (L.hold ? `, ${fmt(100 * L.hold, 0)} % of the hold` : "") + (L.sigma_mg != null ? `, σ of |a| ${fmt(L.sigma_mg * 1000, 0)} µg` : "")
          : "in no planned attitude";
      }
      $(".verdict-text", t).textContent = v;
      t.title = v;
    }
    for (const k of Object.keys(cols)) cols[k].classList.toggle("closed", selected !== k);
  }

  function column(key) {
    if (cols[key]) return cols[key];
    const el = $("#board-tpl").content.firstElementChild.cloneNode(true);
    el.dataset.key = key;
    $(".stop", el).onclick = () => post("/api/stop", { key: key }).catch((e) => alert(e.message));
    $(".resume", el).onclick = () => post("/api/resume", { key: key }).catch((e) => alert(e.message));
    $(".warm-stop", el).onclick = () => post("/api/stop", { key: key }).catch((e) => alert(e.message));
    $(".warm-start", el).onclick = () => {
      $(".warm-error", el).textContent = "";
      startWarmup(key, $(".warm-lo", el).value, $(".warm-hi", el).value, $(".warm-face", el).value,
        $(".warm-write", el).checked).catch((e) => { $(".warm-error", el).textContent = e.message; });
    };
    $("#boards").appendChild(el);
    cols[key] = el;
    return el;
  }

  function renderBoard(b) {
    const el = column(b.key);
    const slot = b.device && b.device.slot ? `slot ${b.device.slot}: ` : "";
    const parts = b.device && b.device.parts ? ` (${b.device.parts.join(", ")})` : "";
    const dev = b.device && b.device.board ? ` — ${b.device.board} ${b.device.uid || ""}${parts}` : b.device && b.device.uid ? ` — ${b.device.uid}` : "";
    $(".devname", el).textContent = slot + (b.key === "sim" ? "virtual bench" : b.device && b.device.slot ? (b.device.url || b.key) : b.key) + dev;
    const st = $(".status", el);
    st.textContent = (gone && b.status === "running" ? "stopped (the station is gone)" : b.status) + (b.phase && b.status === "running" && !gone ? " · " + b.phase : "");
    st.className = "status pill " + b.status;
    const ow = $(".owner", el);
    ow.textContent = b.yours ? "you drive this device" : b.owned ? "read-only: driven from another page" : "";
    ow.className = "owner pill" + (b.owned && !b.yours ? " readonly-banner" : "");
    el.classList.toggle("readonly", b.owned && !b.yours);
    $(".stop", el).hidden = !(b.yours && b.status === "running" && b.phase !== "warmup");   // a warm-up has its own
    $(".resume", el).hidden = !(b.yours && b.resumable && b.status !== "running");
    $(".error-line", el).textContent = b.error && !b.result ? b.error + (b.resumable ? " — the captured attitudes are kept: Resume continues" : "") : "";

    // verdict first
    const v = $(".verdict", el);
    if (b.result) {
      v.hidden = false;
      v.className = "verdict " + b.result.status;
      v.innerHTML = `<b>${b.result.status === "pass" ? "PASSED" : b.result.status === "stopped" ? "STOPPED" : "FAILED"}</b>: ${esc(b.result.verdict)}`;
    } else v.hidden = true;

    renderWarmup(el, b);
    renderLive(el, b);
    renderTargets(el, b);
    renderCards(el, b);

    const res = $(".result", el);
    if (b.result) {
      res.hidden = false;
      $(".params", el).innerHTML = b.result.parameters.map((r) => `<tr><td>${esc(r[0])}</td><td>${esc(r[1])}</td></tr>`).join("");
      $(".result h3", el).textContent = b.result.parameters.length ? "Parameters ± 1σ" : "Nothing was fitted";
      $(".report-line", el).innerHTML = `${b.result.attitudes} attitudes` +
        (b.result.bench_time_s != null ? `, bench time ${fmt(b.result.bench_time_s, 0)} s` : "") + "; " +
        (b.result.report ? `<a class="report-link" href="#" data-report="${esc(b.result.report)}">the HTML report</a>` : "no report (nothing was fitted)") +
        (b.result.history ? `; ${esc(b.result.history)}` : "") +
        ((b.result.exports || []).length ? `<br><small>for other tools: ` + b.result.exports.map((e) => e.url
          ? `<a class="export-link" href="#" data-export="${esc(e.url)}" download="${esc(e.name)}" title="${esc(e.name)}${e.consumer ? " for " + esc(e.consumer) : ""}">${esc(e.label || e.name)}</a>`
          : esc(e.name)).join(", ") + `</small>` : "") +
        `<br><small>session directory ${esc(b.result.session_dir)}</small>`;
    } else res.hidden = true;
    $(".log", el).textContent = b.log.join("\n");
  }

  function renderLive(el, b) {
    const posing = b.status === "running" && (b.phase === "poses" || b.phase === "rest");
    const L = posing ? b.live || {} : {};
    $(".live", el).classList.toggle("idle", b.status !== "running");
    $(".a-g", el).textContent = L.a_g == null ? "–" : Number(L.a_g).toFixed(4);
    const att = $(".attitude", el);
    if (b.phase === "rest") att.textContent = "hold still: measuring the noise" + (L.rest != null ? ` (${fmt(100 * L.rest, 0)} %)` : "");
    else if (L.attitude) att.innerHTML = `the board is in <b>${esc(L.attitude)}</b>: ${esc(L.words)}${L.captured ? " (already captured)" : ""}`;
    else if (b.status === "running" && !posing) att.textContent = {
      turns: b.turns.length && b.turns[b.turns.length - 1].by_hand ? "turn the board by hand one full turn on the table, then let it lie still"
        : b.config && b.config.gyro === "turns" ? "lay the board on the table as shown under the parameters, still" : "the turntable turns the board: keep it mounted, hands off",
      fit: "fitting…",
      write: "writing the parameters to the device…", verify: "verifying: present the attitude asked for below",
      start: "starting…"}[b.phase] || b.phase;
    else if (b.status !== "running") att.textContent = b.status === "done" ? "session finished" : b.status === "idle" ? "–" : "session " + b.status;
    else att.textContent = L.state ? (L.state === "moving" ? "moving…" : "in no planned attitude") : "–";
    const k = L.k || 3, km = L.k_move || 6, r = L.ratio || 0;
    const span = km * 1.25;
    const fill = $(".meter-fill", el);
    fill.style.width = Math.min(100, (100 * r) / span) + "%";
    fill.className = "meter-fill" + (r > km ? " moving" : r > k ? " loud" : "");
    $(".meter-threshold", el).style.left = (100 * k) / span + "%";
    $(".ratio", el).textContent = L.ratio == null ? "" : `${fmt(r, 1)} (still below ${fmt(k, 1)}, from the rest noise) — ${L.state}`;
    $(".hold-fill", el).style.width = fmt(100 * (L.hold || 0), 0) + "%";
    const sig = L.sigma_mg != null ? `σ of |a| ${fmt(L.sigma_mg * 1000, 0)} µg` + (L.target_mg ? ` (target ${fmt(L.target_mg * 1000, 0)} µg)` : "") : "";
    $(".hold-text", el).textContent = sig;
    $(".hint", el).textContent = L.hint || "";
  }

  const UNITS = { b: "mg", s: "ppm", a: "mrad" };
  function renderTargets(el, b) {
    const T = b.targets || {};
    const tbl = $(".targets", el);
    if (T.sigmas) {
      const tgt = (n) => (n[0] === "b" ? T.targets.accel_bias_mg : n[0] === "s" ? T.targets.accel_scale_ppm : T.targets.accel_nonorth_mrad);
      tbl.innerHTML = "<tr><th>accelerometer</th><th>1σ now</th><th>target</th></tr>" + Object.keys(T.sigmas).map((n) =>
        `<tr><td>${n} (${UNITS[n[0]]})</td><td class="${T.sigmas[n] <= tgt(n) ? "ok" : "over"}">${Number(T.sigmas[n]).toPrecision(2)}</td><td>≤ ${tgt(n)}</td></tr>`).join("") +
        `<tr><td colspan="3">${T.reached ? "every parameter at its target: no more attitudes needed" : "more attitudes needed"}</td></tr>`;
    } else tbl.innerHTML = b.config && b.config.capture === "adaptive" && b.method === "multi"
      ? "<tr><td>the parameters' σ appear once 12 attitudes are captured</td></tr>" : "";
    $(".steps", el).innerHTML = b.steps.map((s) => `<div class="step ${esc(s.state)}" data-kind="${esc(s.kind)}">${esc(s.text)}</div>`).join("");
    $(".turns", el).innerHTML = b.turns.map((t, i) => t.by_hand
      ? `<div class="step ${esc(t.state)}"><img alt="turn by hand" data-src="/turn.svg?axis=${t.axis.join(",")}&angle=${t.angle_deg}"> turn ${i + 1}${t.total ? " of " + t.total : ""}: ` +
        `by hand, one full turn (${fmt(t.angle_deg, 0)}°) on the table about the vertical (${"XYZ"[t.axis.map(Math.abs).indexOf(Math.max(...t.axis.map(Math.abs)))]} pointing up), then let it lie still</div>`
      : `<div class="step ${esc(t.state)}"><img alt="turn" data-src="/turn.svg?axis=${t.axis.join(",")}&rate=${t.rate_dps}"> turn ${i + 1}${t.total ? " of " + t.total : ""}: ` +
        `${fmt(t.rate_dps, 0)} °/s about board [${t.axis.map((x) => fmt(x, 0)).join(", ")}] for ${fmt(t.duration_s, 1)} s</div>`).join("");
  }

  // ------------------------------------------------------------------ a temperature warm-up
  // run_warmup's progress (procedures.warmup: elapsed_s, temp_c[4], rate_c_per_min[4],
  // span_c[4][2], fit per triad {order, heldout_rms}), then its result
  // the four temperatures, named with the parts the board reported (b.device.parts: accel, gyro X, Y, Z)
  function sensorNames(b) {
    const p = (b && b.device && b.device.parts) || [];
    return [p[0] || "accelerometer"].concat(["X", "Y", "Z"].map((a, i) => `gyro ${a}` + (p[i + 1] ? ` ${p[i + 1]}` : "")));
  }
  async function startWarmup(port, lo, hi, face, write) {
    const body = { port: port, span_lo_c: Number(lo), span_hi_c: Number(hi), face: face, write: !!write };
    if (!isFinite(body.span_lo_c) || !isFinite(body.span_hi_c) || lo === "" || hi === "") throw new Error("give the span as two temperatures in °C");
    if (!(await claim(port))) throw new Error(port + " is driven from another page");
    return post("/api/warmup", body);
  }

  // a held-out error in the triad's unit: accelerometer m/s² -> mg, gyro rad/s -> m°/s
  function errText(name, v) {
    if (v == null || !isFinite(v)) return "–";
    if (/acc/i.test(name)) return `${fmt(v / 9.80665e-3, 3)} mg`;
    if (/gyr/i.test(name)) return `${fmt(v * 180 / Math.PI * 1000, 2)} m°/s`;
    return Number(v).toPrecision(2);
  }

  function fitRows(fit) {
    // per triad: {order, heldout_rms} (numbers or one per axis), or a list of those per axis
    const rows = [];
    for (const [name, f] of Object.entries(fit || {})) {
      const per = Array.isArray(f) ? f : f && Array.isArray(f.order)
        ? f.order.map((o, i) => ({ order: o, heldout_rms: (f.heldout_rms || [])[i], sigma: (f.sigma || [])[i] })) : null;
      if (per) per.forEach((x, i) => rows.push([`${name} ${"XYZ"[i] !== undefined ? "XYZ"[i] : i}`, x || {}]));
      else rows.push([name, f || {}]);
    }
    return rows;
  }

  function renderWarmup(el, b) {
    const W = b.warmup || {};
    const mine = b.yours || !b.owned;
    const running = b.status === "running" && b.phase === "warmup";
    el.classList.toggle("warming", !!W.config && !b.plan.length);
    $(".warm-stop", el).hidden = !(b.yours && running);
    $(".warm-form", el).hidden = !(mine && b.status !== "running");
    const st = $(".warm-state", el);
    st.textContent = W.config ? (running ? "running" : W.result ? (W.result.stopped ? "stopped, fit kept" : "done") : b.status) : "";
    st.className = "warm-state pill " + (running ? "running" : W.result ? "done" : b.status === "failed" ? "failed" : "");
    st.hidden = !W.config;
    const live = $(".warm-live", el);
    live.hidden = !W.config;
    if (!W.config) return;
    const C = W.config, P = W.progress || {}, R = W.result;
    const lo = C.span_lo_c, hi = C.span_hi_c;
    const el_s = P.elapsed_s;
    const mm = el_s == null ? "–" : `${Math.floor(el_s / 60)} min ${fmt(el_s % 60, 0).padStart(2, "0")} s`;
    $(".warm-summary", el).innerHTML = (R ? `<b>${esc(R.verdict)}</b>. ` : running ? "The board lies still, " +
      `${esc(C.face)} up, while it warms: ` : "") + `span asked ${fmt(lo, 0)}–${fmt(hi, 0)} °C; ${mm} of device time` +
      (running ? "; it stops when every sensor has covered the span or the temperatures stop rising" : "");
    const T = P.temp_c || [], Rt = P.rate_c_per_min || [], S = P.span_c || [];
    const bars = [];
    let rows = "<tr><th>sensor</th><th>now</th><th>rate</th><th>covered</th><th>of the span asked</th></tr>";
    const SENSORS = sensorNames(b);
    for (let i = 0; i < 4; i++) {
      const s = S[i] || [null, null];
      const a = s[0] == null ? 0 : Math.max(0, Math.min(1, (s[0] - lo) / (hi - lo)));
      const z = s[1] == null ? 0 : Math.max(0, Math.min(1, (s[1] - lo) / (hi - lo)));
      const now = T[i] == null ? null : Math.max(0, Math.min(1, (T[i] - lo) / (hi - lo)));
      const full = s[0] != null && s[0] <= lo + 0.5 && s[1] >= hi - 0.5;
      const r = Rt[i];
      rows += `<tr><td>${esc(SENSORS[i])}</td><td>${fmt(T[i], 2)} °C</td>` +
        `<td class="${r == null ? "" : Math.abs(r) < (C.stop_rate_c_per_min || 0.05) ? "flat" : "rising"}">${r == null ? "–" : (r >= 0 ? "+" : "") + fmt(r, 2)} °C/min</td>` +
        `<td>${s[0] == null ? "–" : `${fmt(s[0], 1)}–${fmt(s[1], 1)} °C`}</td>` +
        `<td class="span-cell"><div class="span-bar"><div class="span-covered${full ? " full" : ""}"></div>` +
        `<div class="span-now"${now == null ? " hidden" : ""}></div></div></td></tr>`;
      bars.push([a, z, now]);
    }
    const tbl = $(".warm-temps", el);
    tbl.innerHTML = rows;
    // positions through the CSSOM: the page's Content-Security-Policy refuses inline style attributes
    tbl.querySelectorAll(".span-bar").forEach((bar, i) => {
      const [a, z, now] = bars[i];
      bar.firstElementChild.style.left = fmt(100 * a, 1) + "%";
      bar.firstElementChild.style.width = fmt(100 * Math.max(0, z - a), 1) + "%";
      if (now != null) bar.lastElementChild.style.left = `calc(${fmt(100 * now, 1)}% - 1px)`;
    });
    const fit = (R && R.fit) || P.fit;
    const fr = fitRows(fit);
    const sig = fr.some(([, f]) => f.sigma_over_span != null);
    $(".warm-fit", el).innerHTML = fr.length ? "<tr><th>bias against temperature</th><th>order</th><th>held-out error</th>" +
      (sig ? "<th>1σ of the curve</th>" : "") + "</tr>" +
      fr.map(([n, f]) => `<tr><td>${esc(n)}</td><td>${f.order == null ? "–" : esc(f.order)}</td><td>${errText(n, f.heldout_rms)}</td>` +
        (sig ? `<td>${errText(n, f.sigma_over_span)}</td>` : "") + "</tr>").join("")
      : `<tr><td>${running ? "the fit appears once the temperatures have moved" : "nothing fitted"}</td></tr>`;
    const notes = [...new Set([...(P.notes || []), ...((R && R.notes) || [])])];
    if (!R && running) notes.push(`one face (${C.face} up): the accelerometer's scale temperature terms need more faces ` +
      "(a cube); the axis along gravity gets its bias and scale terms together, right at this attitude");
    $(".warm-notes", el).innerHTML = notes.map((n) => `<li>${esc(n)}</li>`).join("");
    $(".warm-files", el).textContent = R ? `saved: ${R.thermal_json}` : W.dir ? `recording in ${W.dir}` : "";
  }

  function renderCards(el, b) {
    const box = $(".cards", el);
    const done = b.plan.filter((c) => c.state === "done").length;
    const order = b.config && b.config.fixture ? "the plate presents what the boards still need, the most shared first" : "present them in any order";
    $(".cards-title", el).textContent = b.plan.length ? `Attitudes: ${done} of ${b.plan.length} captured — ${order}` +
      (b.config && b.config.capture === "adaptive" && b.method === "multi" ? "; the session stops as soon as the targets are reached" : "") : "";
    const here = (b.live || {}).attitude;
    for (const c of b.plan) {
      let card = box.querySelector(`[data-name="${CSS.escape(c.name)}"]`);
      if (!card) {
        card = document.createElement("div");
        card.className = "card";
        card.dataset.name = c.name;
        card.innerHTML = `<span class="seq"></span><img alt="${esc(c.name)}" data-src="/pose.svg?up=${c.direction.join(",")}">` +
          `<div class="name">${esc(c.name)}</div><div class="words">${esc(c.words)}</div>` +
          `<div class="state"></div><div class="bar"><div class="bar-fill"></div></div><div class="detail"></div>`;
        box.appendChild(card);
      }
      const id = b.key + "/" + c.name;
      if (cardStates[id] !== c.state) { window.__transitions.push([b.key, c.name, c.state]); cardStates[id] = c.state; }
      card.dataset.state = c.state;
      card.dataset.seq = c.seq == null ? "" : c.seq;
      card.className = "card " + c.state + (c.name === here && b.status === "running" ? " here" : "") +
        (b.status === "done" && c.state === "todo" ? " unneeded" : "") +
        (b.status === "running" && c.state === "todo" && c.name === b.suggested ? " suggested" : "");
      $(".seq", card).textContent = c.seq == null ? "" : "#" + c.seq;
      $(".state", card).textContent = c.state === "todo" ? (b.status === "done" ? "not needed" :
        c.name === b.suggested && b.status === "running" ? "to do — suggested next" : "to do") :
        c.state === "capturing" ? "capturing — hold still" : c.state;
      $(".bar-fill", card).style.width = fmt(100 * (c.progress || 0), 0) + "%";
      let d = "";
      if (c.state === "done" && c.before_g != null) d = `|a| ${fmt(c.before_g, 4)} g` + (c.after_g != null ? ` → ${fmt(c.after_g, 5)} g` : "");
      if (c.state === "rejected") d = "rejected: " + esc(c.why);
      $(".detail", card).innerHTML = d;
    }
  }

  // ------------------------------------------------------------------ setup form
  $("#method").onchange = () => { $("#six-warning").hidden = $("#method").value !== "six"; };
  $("#use-sim").onchange = () => { $("#port").disabled = $("#use-sim").checked; };
  $("#setup-form").onsubmit = async (ev) => {
    ev.preventDefault();
    const f = new FormData(ev.target);
    const opts = Object.fromEntries(f.entries());
    opts.port = $("#use-sim").checked ? "sim" : (opts.port || "").trim();
    opts.write = f.get("write") === "on";
    $("#setup-error").textContent = "";
    try {
      if (!opts.port) throw new Error("give the device's port, or choose the virtual bench");
      if (!(await claim(opts.port))) throw new Error(opts.port + " is driven from another page");
      await post("/api/start", opts);
    } catch (e) { $("#setup-error").textContent = e.message; }
  };

  $("#start-warmup").onclick = async () => {
    $("#setup-error").textContent = "";
    const port = $("#use-sim").checked ? "sim" : ($("#port").value || "").trim();
    try {
      if (!port) throw new Error("give the device's port, or choose the virtual bench");
      await startWarmup(port, $("#warm-lo").value, $("#warm-hi").value, $("#warm-face").value,
        $("#setup-form").elements.write.checked);
    } catch (e) { $("#setup-error").textContent = e.message; }
  };

  // the session first (the secret in the address), then the state and its live updates
  openSession().then(() => {
    getJSON("/api/state").then((s) => { if (!last) { last = s; render(s); } }).catch(() => {});
    reconnect();
  }).catch((e) => { $("#conn").textContent = "no session: " + e.message; });
})();
