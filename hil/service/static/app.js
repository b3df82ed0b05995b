// The live page of `hil serve` (docs/service.md, "The live page"): plain JS, no build step, nothing from the
// network but this service. The status and the running item's live points come over the WebSocket /ws; the
// queue and the history from the HTTP API when the status says they changed (and now and then besides).
"use strict";

(function () {
  const WINDOW_S = 10; // the charts' sliding window
  // one redraw of the four charts a second: a 10 s window moves a tenth of its width, and a page costs ~4 % of a
  // core in software rendering (docs/performance.md, "Watching the bench"; 2 a second cost ~6 %, 5 a second ~11 %)
  const DRAW_HZ = 1;
  const LAG_KEEP = 2000;
  const STALE_MS = 5000; // the service sends its status every second: silence this long is a dead socket
  const BACKOFF_MS = [500, 1000, 2000, 4000, 8000, 10000];

  const page = { drawHz: DRAW_HZ, points: 0, lastCycles: 0, lagMs: [], errors: [], frames: 0, last: null, charts: {},
                 status: null, connected: false };
  window.hilPage = page;

  // The token lives in the hil_token cookie, which the browser sends with every request and the WebSocket of this
  // service only, never in the URL (kept in histories and logs). A page opened as /?token=... moves it there at once.
  function useToken(value) {
    document.cookie = "hil_token=" + encodeURIComponent(value) + "; path=/; SameSite=Strict";
  }
  const given = new URLSearchParams(location.search).get("token");
  if (given) {
    useToken(given);
    history.replaceState(null, "", location.pathname + location.hash);
  }

  const $ = (id) => document.getElementById(id);

  function noteError(what) {
    page.errors.push(String(what));
    if (page.errors.length > 100) page.errors.splice(0, page.errors.length - 100);
  }
  window.addEventListener("error", (e) => noteError(e.message || e));
  window.addEventListener("unhandledrejection", (e) => noteError(e.reason && e.reason.message || e.reason));

  // --- little helpers ---------------------------------------------------------------------------

  function el(tag, attrs, ...children) {
    const node = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v === undefined || v === null) continue;
      if (k === "class") node.className = v;
      else if (k === "text") node.textContent = v;
      else node.setAttribute(k, v);
    }
    for (const c of children) node.append(c);
    return node;
  }

  function when(iso) {
    if (!iso) return "";
    const d = new Date(iso);
    if (isNaN(d)) return String(iso);
    const time = d.toLocaleTimeString([], { hour12: false });
    const today = new Date();
    return d.toDateString() === today.toDateString() ? time : d.toISOString().slice(0, 10) + " " + time;
  }

  function span(seconds) {
    if (seconds === null || seconds === undefined || !isFinite(seconds)) return "";
    seconds = Math.max(0, Math.round(seconds));
    const h = Math.floor(seconds / 3600), m = Math.floor(seconds / 60) % 60, s = seconds % 60;
    const two = (n) => String(n).padStart(2, "0");
    return h ? `${h}:${two(m)}:${two(s)}` : `${m}:${two(s)}`;
  }

  function num(v, digits) {
    return typeof v === "number" && isFinite(v) ? v.toFixed(digits) : "";
  }

  async function api(method, path, body) {
    const headers = { Accept: "application/json" };
    if (body !== undefined) headers["Content-Type"] = "application/json";
    const res = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body),
                                    cache: "no-store" });
    let data = null;
    try { data = await res.json(); } catch (_) { data = null; }
    if (!res.ok) throw new Error((data && data.detail) || `${method} ${path}: HTTP ${res.status}`);
    return data;
  }

  // a text set only when it changed: an unchanged assignment still makes the browser lay out and paint again
  function setText(id, text) {
    const node = $(id);
    if (node.textContent !== text) node.textContent = text;
  }

  function showNotice(text) {
    const n = $("notice");
    n.textContent = text || "";
    n.hidden = !text;
  }

  // --- the charts -------------------------------------------------------------------------------

  const COLORS = { a: "#1f6fb4", b: "#e0701b", c: "#2a9d48", d: "#c0392b", e: "#7d4cb0", f: "#8c5a2b" };

  function timeSeries() {
    return { label: "time", value: (u, v) => (v === null || v === undefined ? "" :
      new Date(v * 1000).toLocaleTimeString([], { hour12: false }) + "." +
      String(Math.floor((v * 1000) % 1000)).padStart(3, "0")) };
  }

  function line(label, color, scale, dash) {
    return { label, stroke: color, width: 1, scale: scale || "y", dash, spanGaps: false,
             value: (u, v) => (v === null || v === undefined ? "–" : v.toFixed(Math.abs(v) >= 100 ? 0 : 2)) };
  }

  // a y range with a little room; a flat trace (a hexapod axis at home) gets +-1 unit, not 0..100
  function yRange(u, min, max) {
    if (min === null || max === null || !isFinite(min) || !isFinite(max)) return [-1, 1];
    if (max - min < 1e-9) return [min - 1, max + 1];
    return uPlot.rangeNum(min, max, 0.1, true);
  }

  function yAxis(label, scale, side) {
    return { scale: scale || "y", label, labelSize: 18, size: 60, side: side || 3,
             grid: { show: side !== 1, stroke: "#e6e8eb", width: 1 }, ticks: { stroke: "#d0d4d9", width: 1 } };
  }

  const clock = (v) => new Date(v * 1000).toLocaleTimeString([], { hour12: false });
  const xAxis = { label: "time of day (h:m:s)", labelSize: 18, grid: { stroke: "#e6e8eb", width: 1 },
                  ticks: { stroke: "#d0d4d9", width: 1 }, space: 70,
                  values: (u, splits) => splits.map((v) => (v === null || v === undefined ? "" : clock(v))) };

  // each chart: its uPlot series and, for each, where a live point keeps the value
  const CHARTS = {
    rate: { target: "chart-rate", series: [line("el (deg/s)", COLORS.a), line("az (deg/s)", COLORS.b)],
            axes: [yAxis("rate error (deg/s)")],
            get: [(p) => p.loop && p.loop.rate_err_el_dps, (p) => p.loop && p.loop.rate_err_az_dps] },
    drive: { target: "chart-drive", series: [line("el (counts)", COLORS.a), line("az (counts)", COLORS.b)],
             axes: [yAxis("drive (counts)")],
             get: [(p) => p.loop && p.loop.drive_el_counts, (p) => p.loop && p.loop.drive_az_counts] },
    miss: { target: "chart-miss", series: [line("x (px)", COLORS.a), line("y (px)", COLORS.b)],
            axes: [yAxis("miss distance (px)")],
            get: [(p) => p.image && p.image.miss_x_px, (p) => p.image && p.image.miss_y_px] },
    pose: { target: "chart-pose",
            series: [line("x (mm)", COLORS.a, "mm"), line("y (mm)", COLORS.b, "mm"), line("z (mm)", COLORS.c, "mm"),
                     line("roll (deg)", COLORS.d, "deg", [5, 3]), line("pitch (deg)", COLORS.e, "deg", [5, 3]),
                     line("yaw (deg)", COLORS.f, "deg", [5, 3])],
            axes: [yAxis("position (mm)", "mm"), yAxis("rotation (deg)", "deg", 1)],
            scales: { mm: { auto: true, range: yRange }, deg: { auto: true, range: yRange } },
            get: [(p) => p.hexapod && p.hexapod.x_mm, (p) => p.hexapod && p.hexapod.y_mm,
                  (p) => p.hexapod && p.hexapod.z_mm, (p) => p.hexapod && p.hexapod.roll_deg,
                  (p) => p.hexapod && p.hexapod.pitch_deg, (p) => p.hexapod && p.hexapod.yaw_deg] },
  };

  const buffers = { uid: null, x: [], cols: {} }; // the sliding window, shared x (the manager's wall clock, s)
  let pending = []; // points received, not yet plotted

  function chartWidth(node) {
    return Math.max(280, Math.floor(node.parentElement.clientWidth - 4));
  }

  function makeCharts() {
    for (const [name, spec] of Object.entries(CHARTS)) {
      const node = $(spec.target);
      const opts = {
        width: chartWidth(node), height: 210,
        scales: Object.assign({
          x: { time: true, range: (u, min, max) => {
            const hi = max === null || max === undefined ? Date.now() / 1000 : max;
            return [hi - WINDOW_S, hi];
          } },
          y: { auto: true, range: yRange },
        }, spec.scales || {}),
        series: [timeSeries(), ...spec.series],
        axes: [xAxis, ...spec.axes],
        legend: { live: true },
        cursor: { drag: { x: false, y: false } },
      };
      buffers.cols[name] = spec.series.map(() => []);
      page.charts[name] = new uPlot(opts, [buffers.x, ...buffers.cols[name]], node);
    }
    const resize = () => {
      for (const [name, spec] of Object.entries(CHARTS)) {
        const u = page.charts[name];
        const w = chartWidth($(spec.target));
        if (u && Math.abs(u.width - w) > 2) u.setSize({ width: w, height: 210 });
      }
    };
    if (window.ResizeObserver) new ResizeObserver(resize).observe($("charts-card"));
    else window.addEventListener("resize", resize);
  }

  function clearBuffers(uid) {
    buffers.uid = uid;
    buffers.x.length = 0;
    for (const cols of Object.values(buffers.cols)) for (const c of cols) c.length = 0;
  }

  const finiteOrNull = (v) => (typeof v === "number" && isFinite(v) ? v : null);

  // At most page.drawHz (DRAW_HZ) redraws a second, each of the whole 10 s window; points are kept as they arrive
  // and drawn in batches.
  // A hidden tab draws nothing: its window is kept up to date and drawn once when it shows again.
  let drawTimer = null, lastDrawMs = 0;

  function schedule() {
    if (drawTimer !== null) return;
    const wait = document.hidden ? 1000 : Math.max(0, lastDrawMs + 1000 / page.drawHz - Date.now());
    drawTimer = setTimeout(flush, wait);
  }

  function flush() {
    drawTimer = null;
    const batch = pending;
    pending = [];
    try {
      const last = ingest(batch);
      if (document.hidden) return;
      if (last || page.stale) draw(last);
    } catch (e) {
      noteError("plot: " + (e && e.message || e));
    }
  }

  document.addEventListener("visibilitychange", () => { if (!document.hidden) { page.stale = true; schedule(); } });

  // the points into the sliding window; the last one taken (null: none)
  function ingest(batch) {
    const now = Date.now();
    let last = null;
    for (const p of batch) {
      if (p.uid !== buffers.uid) clearBuffers(p.uid);
      const t = p.wall_ms / 1000;
      if (buffers.x.length && t <= buffers.x[buffers.x.length - 1]) continue; // uPlot wants x increasing
      buffers.x.push(t);
      for (const [name, spec] of Object.entries(CHARTS)) {
        const cols = buffers.cols[name];
        spec.get.forEach((get, i) => cols[i].push(finiteOrNull(get(p))));
      }
      page.lagMs.push(now - p.wall_ms);
      page.points += 1;
      if (typeof p.cycles === "number") page.lastCycles = p.cycles;
      last = p;
    }
    if (page.lagMs.length > LAG_KEEP) page.lagMs.splice(0, page.lagMs.length - LAG_KEEP);
    if (!last) return null;
    page.stale = true;
    // the sliding window: drop what is older than WINDOW_S (plus a margin, so the left edge stays drawn)
    const oldest = buffers.x[buffers.x.length - 1] - WINDOW_S - 1;
    let cut = 0;
    while (cut < buffers.x.length && buffers.x[cut] < oldest) cut++;
    if (cut) {
      buffers.x.splice(0, cut);
      for (const cols of Object.values(buffers.cols)) for (const c of cols) c.splice(0, cut);
    }
    page.last = { uid: last.uid, cycles: last.cycles, wall_ms: last.wall_ms, armed: last.armed };
    for (const [name, spec] of Object.entries(CHARTS)) {
      spec.series.forEach((s, i) => { page.last[name + ":" + s.label] = buffers.cols[name][i][buffers.x.length - 1]; });
    }
    return last;
  }

  function draw(last) {
    page.stale = false;
    lastDrawMs = Date.now();
    for (const name of Object.keys(CHARTS)) {
      const u = page.charts[name];
      u.setData([buffers.x, ...buffers.cols[name]]);
      // the legend reads the latest values unless the cursor is on the chart
      if (!(u.cursor.left >= 0)) u.setLegend({ idx: buffers.x.length - 1 });
    }
    page.frames += 1;
    if (last) showLoopState(last);
  }

  function showLoopState(p) {
    const st = page.status;
    if (!st || !st.running || st.running.uid !== p.uid) return;
    const running = st.running;
    const total = running.total || p.total || 0;
    showProgress(p.cycles || 0, total);
    const armed = p.armed === undefined ? "" : p.armed ? "loop armed" : "loop not armed";
    setText("run-state", [armed, endingText(running.ending)].filter(Boolean).join(" · "));
  }

  // --- the status -------------------------------------------------------------------------------

  function endingText(ending) {
    return ending === "stop" ? "stop asked: winding down" : ending === "abort" ? "abort asked: driver disabled first" : "";
  }

  function showProgress(cycles, total) {
    const frac = total > 0 ? Math.min(1, cycles / total) : 0;
    $("run-bar").style.width = (100 * frac).toFixed(1) + "%";
    $("run-progress").textContent = total > 0
      ? `${cycles.toLocaleString()} / ${total.toLocaleString()} cycles (${(100 * frac).toFixed(0)} %)` +
        (cycles > total ? " · winding down" : "")
      : cycles > 0 ? `${cycles.toLocaleString()} cycles` : "starting";
  }

  function badge(text, kind) {
    return el("span", { class: "badge " + (kind || ""), text });
  }

  function yesNo(value, yes, no, badWhenNo) {
    if (value === true) return badge(yes, "ok");
    if (value === false) return badge(no, badWhenNo ? "bad" : "off");
    return badge("?", "off");
  }

  function showBoards(w) {
    const tbody = $("boards").querySelector("tbody");
    tbody.replaceChildren();
    for (const [name, b] of Object.entries(w.boards || {})) {
      tbody.append(el("tr", { "data-board": name, "data-connected": String(b.connected),
                              "data-identified": String(b.identified), "data-armed": String(b.armed) },
        el("th", { text: name }), el("td", { class: "port", text: b.port || "" }),
        el("td", {}, yesNo(b.connected, "connected", "not connected")),
        el("td", {}, yesNo(b.identified, "identified", "not identified", true)),
        el("td", {}, b.armed ? badge("armed", "armed") : badge("disarmed", "off"))));
    }
    if (!Object.keys(w.boards || {}).length) {
      tbody.append(el("tr", {}, el("td", { colspan: "5", class: "muted",
                                           text: w.state === "ready" ? "no boards" : "the worker is " + (w.state || "?") })));
    }
  }

  let lastSig = { queue: null, history: null, boards: null, lease: null };

  function onStatus(st) {
    page.status = st;
    const svc = st.service || {};
    setText("service", [svc.lab, svc.version ? "hil " + svc.version : "", svc.auth].filter(Boolean).join(" · "));
    const you = st.you;
    setText("you", you ? `you: ${you.user} (${you.role})` : "");
    const operator = !!(you && you.role === "operator");

    // the worker
    const w = st.worker || {};
    const ws = $("worker-state");
    setText("worker-state", w.state || "?");
    const wsClass = "badge " + (w.state === "ready" ? "ok" : w.state === "starting" ? "warn" : "bad");
    if (ws.className !== wsClass) ws.className = wsClass;
    $("worker-error").hidden = !w.error;
    setText("worker-error", w.error ? "cannot serve: " + w.error : "");
    setText("worker-holder", w.holder ? "holds the ports: " + w.holder : "");

    // the boards, the lease: redrawn only when they changed (the status comes every second)
    const bsig = JSON.stringify([w.state, w.boards || {}]);
    if (bsig !== lastSig.boards) { lastSig.boards = bsig; showBoards(w); }
    const lease = st.lease;
    const lsig = lease ? `${lease.holder}|${Math.round(lease.remaining_s)}|${lease.ttl_s}` : "";
    if (lsig !== lastSig.lease) {
      lastSig.lease = lsig;
      $("lease").replaceChildren(lease
        ? el("span", {}, "held by ", el("strong", { text: lease.holder }), ` · ${span(lease.remaining_s)} left` +
            (lease.ttl_s ? ` (TTL ${span(lease.ttl_s)})` : "") + ": only the holder's items start")
        : "none: every user's items run in queue order");
    }

    // the running item
    const r = st.running;
    const msg = $("action-msg");
    if (msg.dataset.uid && (!r || r.uid !== msg.dataset.uid)) {
      msg.textContent = "";
      delete msg.dataset.uid;
    }
    $("idle").hidden = !!r;
    $("running").hidden = !r;
    setText("safe", w.safe ? "Between items: " + w.safe + "." :
      (!st.running && w.state === "ready" ? "Between items: measuring the boards' rest state…" : ""));
    if (r) {
      setText("run-name", r.name || r.uid);
      setText("run-kind", r.kind ? "(" + r.kind + ")" : "");
      setText("run-user", r.user || "");
      setText("run-started", when(r.started_at));
      setText("run-uid", r.uid);
      if (!(page.last && page.last.uid === r.uid)) showProgress(r.cycles || 0, r.total || 0);
      if (!(page.last && page.last.uid === r.uid)) setText("run-state", endingText(r.ending));
      $("controls").hidden = !operator;
      $("stop").disabled = !!r.ending;
      $("abort").disabled = r.ending === "abort";
      setText("live-note", "(last 10 s of " + (r.name || r.uid) + ")");
    } else {
      $("controls").hidden = true;
      if (buffers.uid) setText("live-note", "(the last item's final 10 s; nothing running)");
    }

    // the queue and the history, when they changed
    const q = st.queue || {};
    setText("queue-state", (q.running ? "started" : `stopped (${q.stopped || "stopped"}): nothing starts`) +
      (q.stop_on_failure ? " · stops on a failure" : "") + ` · ${q.waiting || 0} waiting`);
    $("queue-start").hidden = !operator || !!q.running;
    const store = st.store || {};
    if (store.error) showNotice(`The service's state store: ${store.error}`);
    const qsig = `${r ? r.uid : ""}|${q.waiting}`;
    if (qsig !== lastSig.queue) { lastSig.queue = qsig; refreshQueue(); }
    const hsig = r ? r.uid : "";
    if (hsig !== lastSig.history) { lastSig.history = hsig; refreshHistory(); }
  }

  // --- the queue and the history (HTTP) ---------------------------------------------------------

  function single(fn) { // one request at a time; a call meanwhile runs once more after it
    let busy = false, again = false;
    return async function run() {
      if (busy) { again = true; return; }
      busy = true;
      try { await fn(); } catch (e) { noteError(e.message || e); } finally {
        busy = false;
        if (again) { again = false; run(); }
      }
    };
  }

  const refreshQueue = single(async () => {
    const data = await api("GET", "/api/queue");
    const waiting = (data.items || []).filter((i) => !i.started_at);
    const tbody = $("queue").querySelector("tbody");
    tbody.replaceChildren(...waiting.map((i, n) => el("tr", { "data-uid": i.uid },
      el("td", { text: String(n + 1) }), el("td", { text: i.name }), el("td", { text: i.kind }),
      el("td", { text: i.user }), el("td", { text: when(i.submitted_at) }))));
    $("queue-empty").hidden = waiting.length > 0;
    $("queue").hidden = waiting.length === 0;
  });

  const STATUS_CLASS = { completed: "ok", stopped: "warn", aborted: "bad", fault: "bad", interrupted: "off",
                         invalid: "off" };

  const refreshHistory = single(async () => {
    const data = await api("GET", "/api/history?limit=50");
    const records = data.records || [];
    for (const r of records) known.set(r.uid, r);
    const tbody = $("history").querySelector("tbody");
    tbody.replaceChildren(...records.map((r) => {
      const links = r.links || {};
      const pick = el("input", { type: "checkbox", class: "pick", "data-uid": r.uid,
                                 title: links.series ? "select it to compare it with others" : "it left no log to compare",
                                 "aria-label": "compare " + r.name });
      pick.checked = selected.has(r.uid);
      pick.disabled = !links.series;
      const files = el("td", { class: "links" });
      files.append(el("a", { href: links.record || `/api/history/${r.uid}`, target: "_blank", rel: "noopener",
                             text: "record", title: "the record and its summary metrics (JSON)" }));
      if (links.log) files.append(" ", el("a", { href: links.log, class: "log", text: "log",
                                                 title: "the session's log (HDF5)" }));
      if (links.report) files.append(" ", el("a", { href: links.report, target: "_blank", rel: "noopener",
                                                    class: "report", text: "report" }));
      const took = r.started_at && r.ended_at ? (new Date(r.ended_at) - new Date(r.started_at)) / 1000 : null;
      const sigma = r.summary && r.summary.rate_error_el_dps ? r.summary.rate_error_el_dps.std : null;
      return el("tr", { "data-uid": r.uid, "data-status": r.status, class: links.series ? "openable" : null,
                        title: links.series ? "open its plots and metrics" : null },
        el("td", {}, pick), el("td", { text: r.name }), el("td", { text: r.kind }), el("td", { text: r.user }),
        el("td", {}, badge(r.status, STATUS_CLASS[r.status] || "off")),
        el("td", { text: when(r.started_at) }), el("td", { text: when(r.ended_at) }), el("td", { text: span(took) }),
        el("td", { class: "num", text: r.exit_code === null || r.exit_code === undefined ? "" : String(r.exit_code) }),
        el("td", { class: "num", text: sigma === null ? "" : num(sigma, 2) + " deg/s" }),
        el("td", { class: "message", text: r.message || "", title: r.message || "" }), files);
    }));
    const last = records[0];
    $("last-item").replaceChildren(...(last ? ["The last item: ", el("strong", { text: last.name }), " by " + last.user + " ",
      badge(last.status, STATUS_CLASS[last.status] || "off"), " at " + when(last.ended_at)] : []));
    $("history-empty").hidden = records.length > 0;
    $("history").hidden = records.length === 0;
    showSelection();
  });

  // --- results: an ended item's plots and metrics, or several side by side ------------------------

  const RESULT_POINTS = 2000; // per channel, as the service decimates them (their envelope)
  const RESULT_HEIGHT = 240;
  const SERIES_KEEP = 20; // items whose series stay in memory
  const DASHES = [undefined, [6, 3], [2, 3], [10, 3, 2, 3]]; // item 1, 2, ... of a comparison
  const LINE_COLORS = Object.values(COLORS);
  const known = new Map(); // uid -> its history record (also those scrolled out of the last 50)
  const selected = new Set(); // uids ticked for a comparison
  const seriesCache = new Map(); // uid -> its series (an ended item's log does not change)
  page.results = { uids: [], charts: {}, metrics: null, ready: false };
  let resultsAsked = 0;

  function showSelection() {
    const n = [...selected].filter((uid) => known.has(uid)).length;
    const button = $("compare");
    button.textContent = `Compare selected (${n})`;
    button.disabled = n < 2;
  }

  $("history").querySelector("tbody").addEventListener("click", (ev) => {
    const target = ev.target;
    if (target.closest("a")) return; // a link does what links do
    if (target.classList.contains("pick")) {
      if (target.checked) selected.add(target.dataset.uid); else selected.delete(target.dataset.uid);
      showSelection();
      return;
    }
    const tr = target.closest("tr[data-uid]");
    const record = tr && known.get(tr.dataset.uid);
    if (record && record.links && record.links.series) showResults([record]);
  });
  $("compare").addEventListener("click", () => {
    const records = [...selected].map((uid) => known.get(uid)).filter(Boolean);
    if (records.length >= 2) showResults(records);
  });
  if (window.ResizeObserver) {
    new ResizeObserver(() => {
      for (const u of Object.values(page.results.charts)) {
        const w = chartWidth(u.root.parentElement);
        if (Math.abs(u.width - w) > 2) u.setSize({ width: w, height: RESULT_HEIGHT });
      }
    }).observe($("results-card"));
  }
  $("results-close").addEventListener("click", () => {
    resultsAsked += 1;
    clearResults();
    $("results-card").hidden = true;
  });

  async function seriesOf(record) {
    if (!seriesCache.has(record.uid)) {
      const series = await api("GET", `${record.links.series}?max_points=${RESULT_POINTS}`);
      seriesCache.set(record.uid, series);
      if (seriesCache.size > SERIES_KEEP) seriesCache.delete(seriesCache.keys().next().value); // the oldest
    }
    return seriesCache.get(record.uid);
  }

  function clearResults() {
    for (const u of Object.values(page.results.charts)) u.destroy();
    page.results = { uids: [], charts: {}, metrics: null, ready: false };
    $("results-charts").replaceChildren();
    $("results-metrics").querySelector("thead").replaceChildren();
    $("results-metrics").querySelector("tbody").replaceChildren();
  }

  async function showResults(records) {
    const asked = ++resultsAsked;
    const card = $("results-card");
    card.hidden = false;
    const many = records.length > 1;
    const tags = records.map((r, i) => (many ? String.fromCharCode(65 + (i % 26)) : ""));
    setText("results-note", many ? `(${records.length} items side by side)` : `(${records[0].name})`);
    setText("results-msg", "reading " + (many ? "their logs…" : "its log…"));
    card.scrollIntoView({ block: "nearest" });
    let all;
    try {
      all = await Promise.all(records.map(seriesOf));
    } catch (e) {
      if (asked !== resultsAsked) return;
      setText("results-msg", "cannot show it: " + (e.message || e));
      noteError(e.message || e);
      return;
    }
    if (asked !== resultsAsked) return; // another item was opened meanwhile
    clearResults();
    $("results-msg").textContent = many ? "Each item's lines are dashed differently (A solid, B dashed, …); "
      + "the colours are the channels." : `${records[0].kind} ${records[0].status} · ${all[0].log}`;
    showMetrics(records, tags, all);
    showResultCharts(tags, all);
    page.results.uids = records.map((r) => r.uid);
    page.results.ready = true;
  }

  function itemTitle(record, tag) {
    return (tag ? tag + ": " : "") + `${record.name} (${record.uid.slice(0, 8)}, ${record.status})`;
  }

  function showMetrics(records, tags, all) {
    const rows = new Map(); // metric -> {unit, values per item}
    all.forEach((series, i) => {
      for (const m of series.metrics || []) {
        if (!rows.has(m.metric)) rows.set(m.metric, { unit: m.unit, values: records.map(() => "") });
        rows.get(m.metric).values[i] = m.value;
      }
    });
    const table = $("results-metrics");
    table.querySelector("thead").replaceChildren(el("tr", {}, el("th", { text: "metric" }), el("th", { text: "unit" }),
      ...records.map((r, i) => el("th", { class: "num", "data-uid": r.uid, text: itemTitle(r, tags[i]) }))));
    table.querySelector("tbody").replaceChildren(...[...rows].map(([metric, row]) => el("tr", {},
      el("td", { text: metric }), el("td", { class: "muted", text: row.unit }),
      ...row.values.map((v) => el("td", { class: "num", text: v })))));
    page.results.metrics = { columns: records.map((r) => r.uid), rows: rows.size };
  }

  function showResultCharts(tags, all) {
    const names = [];
    for (const series of all) for (const c of series.charts || []) if (!names.includes(c.name)) names.push(c.name);
    const box = $("results-charts");
    for (const name of names) {
      const charts = all.map((series) => (series.charts || []).find((c) => c.name === name) || null);
      const first = charts.find(Boolean);
      const scales = { x: { time: false } };
      first.axes.forEach((a, k) => { scales["y" + k] = { auto: true, range: yRange }; });
      const series = [{ label: `${first.x.label} (${first.x.unit})`, value: (u, v) => (v == null ? "" : v.toFixed(3)) }];
      const tables = [];
      charts.forEach((chart, i) => {
        if (!chart) return;
        tables.push([chart.t, ...chart.lines.map((ln) => chart.columns[ln.column])]);
        chart.lines.forEach((ln, k) => {
          const s = line(`${tags[i] ? tags[i] + " " : ""}${ln.label} (${ln.unit})`, LINE_COLORS[k % LINE_COLORS.length],
                         "y" + ln.axis, DASHES[i % DASHES.length]);
          series.push(s);
        });
      });
      const data = tables.length > 1 ? uPlot.join(tables) : tables[0];
      const node = el("div");
      box.append(el("div", { class: "chart", "data-chart": name }, el("h3", { text: first.title }), node));
      const opts = {
        width: chartWidth(node), height: RESULT_HEIGHT, scales, series,
        axes: [{ label: `${first.x.label} (${first.x.unit})`, labelSize: 18, space: 60,
                 grid: { stroke: "#e6e8eb", width: 1 }, ticks: { stroke: "#d0d4d9", width: 1 } },
               ...first.axes.map((a, k) => yAxis(`${a.label} (${a.unit})`, "y" + k, k ? 1 : 3))],
        legend: { live: true },
        cursor: { sync: { key: "hil-results" }, drag: { x: true, y: false } },
      };
      page.results.charts[name] = new uPlot(opts, data, node);
    }
  }

  setInterval(() => { if (page.connected) { refreshQueue(); refreshHistory(); } }, 15000);

  // --- stop and abort ---------------------------------------------------------------------------

  async function end(how) {
    const r = page.status && page.status.running;
    if (!r) return;
    if (how === "abort" && !window.confirm(`Abort ${r.name}? The driver is disabled first; the item ends as aborted, and the queue stops until an operator starts it again.`)) {
      return;
    }
    const msg = $("action-msg");
    msg.dataset.uid = r.uid;
    msg.textContent = how === "stop" ? "asking to stop…" : "asking to abort…";
    try {
      await api("POST", "/api/bench/" + how, { reason: "from the live page", uid: r.uid });
      msg.textContent = how === "stop" ? `stop asked of ${r.name}: it winds down` :
        `abort asked of ${r.name}: the driver is disabled first`;
    } catch (e) {
      msg.textContent = `${how}: ${e.message || e}`;
    }
  }
  $("stop").addEventListener("click", () => end("stop"));
  $("queue-start").addEventListener("click", async () => {
    const q = (page.status && page.status.queue) || {};
    if (!window.confirm(`Start the queue? It was stopped (${q.stopped || ""}); its items then run one after another.`)) return;
    try {
      await api("POST", "/api/queue/start", { stop_on_failure: false });
    } catch (e) {
      setText("action-msg", `start: ${e.message || e}`);
    }
  });
  $("abort").addEventListener("click", () => end("abort"));

  // --- the WebSocket ----------------------------------------------------------------------------

  let socket = null, attempt = 0, lastMessage = 0, retryTimer = null;

  function setConnected(ok, text) {
    page.connected = ok;
    document.body.classList.toggle("disconnected", !ok);
    const c = $("conn");
    c.textContent = text;
    c.className = "badge " + (ok ? "ok" : "bad");
  }

  function connect() {
    retryTimer = null;
    const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
    let ws;
    try {
      ws = new WebSocket(url);
    } catch (e) {
      noteError(e.message || e);
      retry("disconnected");
      return;
    }
    socket = ws;
    ws.onopen = () => {
      attempt = 0;
      lastMessage = Date.now();
      setConnected(true, "connected");
      showNotice("");
      lastSig = { queue: null, history: null, boards: null, lease: null };
    };
    ws.onmessage = (ev) => {
      lastMessage = Date.now();
      let msg;
      try { msg = JSON.parse(ev.data); } catch (e) { noteError("a message that is not JSON"); return; }
      if (msg.type === "status") {
        try { onStatus(msg); } catch (e) { noteError("status: " + (e && e.message || e)); }
      } else if (msg.type === "live" && Array.isArray(msg.points)) {
        for (const p of msg.points) if (p && typeof p.wall_ms === "number") pending.push(p);
        schedule();
      }
    };
    let opened = false;
    ws.addEventListener("open", () => { opened = true; });
    ws.onclose = (ev) => {
      if (socket !== ws) return;
      socket = null;
      if (ev.code === 4401) { // refused: say why, and wait for a token instead of asking again and again
        refused(ev.reason || "no valid token");
        return;
      }
      retry("disconnected");
      if (!opened) whyRefused();
    };
    ws.onerror = () => {}; // onclose follows
  }

  // a socket refused before it opened says nothing: ask the API why
  async function whyRefused() {
    let res;
    try {
      res = await fetch("/api/status", { cache: "no-store" });
    } catch (_) {
      return; // the service is not there: "disconnected" says it
    }
    if (res.status === 400 || res.status === 401 || res.status === 403) {
      let detail = "";
      try { detail = (await res.json()).detail || ""; } catch (_) { detail = ""; }
      refused(`HTTP ${res.status}${detail ? ": " + detail : ""}`);
    }
  }

  // the service refused this page: say why, show the token form, and stop asking until a token is given
  function refused(why) {
    if (retryTimer) { clearTimeout(retryTimer); retryTimer = null; }
    page.refused = why;
    showNotice(`The service refused this page (${why}). Give your token below; it is kept in a cookie of this ` +
               "service, never in the address.");
    setConnected(false, "not authorized");
    $("login").hidden = false;
  }
  $("login").addEventListener("submit", (e) => {
    e.preventDefault();
    const value = $("login-token").value.trim();
    if (!value) return;
    useToken(value);
    $("login-token").value = "";
    $("login").hidden = true;
    page.refused = null;
    attempt = 0;
    connect();
  });

  function retry(why) {
    const wait = BACKOFF_MS[Math.min(attempt, BACKOFF_MS.length - 1)];
    attempt += 1;
    setConnected(false, `${why}: reconnecting in ${(wait / 1000).toFixed(wait < 1000 ? 1 : 0)} s`);
    if (!retryTimer) retryTimer = setTimeout(connect, wait);
  }

  setInterval(() => { // a socket that went silent (a suspended laptop, a dead link) is closed and opened again
    if (socket && page.connected && Date.now() - lastMessage > STALE_MS) {
      const ws = socket;
      socket = null;
      try { ws.close(); } catch (_) { /* closing anyway */ }
      retry("disconnected (no message for 5 s)");
    }
  }, 1000);

  makeCharts();
  connect();
})();
