// Sessions from the telemetry history: device, start, duration, messages, alarms raised, status, and each
// session's files (CSV, Parquet, a plot, a Rerun recording and a USD session, made on demand).
"use strict";

(() => {
  const { el, main } = Twin;
  const LABELS = { csv: "CSV", parquet: "Parquet", png: "plot", rrd: "Rerun .rrd", usd: "USD" };
  const device = el("input", { type: "search", placeholder: "device", "aria-label": "device" });
  const state = el("select", { "aria-label": "status" }, el("option", { value: "", text: "any status" }),
    el("option", { value: "active", text: "active" }), el("option", { value: "completed", text: "completed" }));
  const note = el("span", { class: "counts" });
  const body = el("tbody");
  const fileResult = el("p", { id: "file-result", class: "ack-refused", role: "status", hidden: "" });
  main.append(el("h1", { text: "Sessions" }),
    el("div", { class: "toolbar" }, device, state, el("button", { type: "button", text: "Refresh", onclick: load }), note),
    fileResult,
    el("table", { id: "sessions" }, el("thead", {}, el("tr", {}, ...["device", `start (${Twin.zone()})`, "duration", "messages", "alarms raised", "status", "files"].map((t) => el("th", { text: t })))), body));
  let doc = null;

  function render() {
    if (!doc) return;
    if (!doc.history) {
      body.replaceChildren(el("tr", {}, el("td", { colspan: 7, class: "empty", text: "History is off: set [history] uri in the agent's config to keep sessions (docs/history.md)." })));
      return;
    }
    const q = device.value.trim().toLowerCase(), st = state.value;
    const rows = doc.sessions.filter((s) => (!q || s.device.toLowerCase().includes(q)) && (!st || s.status === st));
    note.textContent = `${rows.length} of ${doc.sessions.length} sessions, newest first · a gap of ${doc.gap_s} s ends one`;
    // "no session yet" under a device box that matched nothing read as an empty history (a walk typed an id
    // that no session has while history held several): the filters are named when they hide every session.
    // A damaged history listed nothing and read "no session yet", as if it held none: the agent's reason.
    const empty = doc.sessions.length
      ? "no session matches these filters (the device box finds part of an id)"
      : doc.unreadable ? `the history cannot be read, so no session is listed: ${doc.unreadable}`
      : "no session yet";
    if (!rows.length) {
      body.replaceChildren(el("tr", {}, el("td", { colspan: 7, class: "empty", text: empty })));
      return;
    }
    body.replaceChildren(...rows.map((s) => {
      const base = `/api/sessions/${encodeURIComponent(s.device)}/${s.key}/`;
      const files = doc.kinds.map((k) => el("a", { href: base + k, download: "", "data-kind": k, text: LABELS[k] || k,
        onclick: (event) => download(event, s, LABELS[k] || k) }));
      // Wraps: seven links on one line ran past a 768 px window.
      const cell = el("td", { class: "wrap files" });
      files.forEach((a, i) => { if (i) cell.append(" · "); cell.append(a); });
      return el("tr", { "data-device": s.device, "data-key": s.key },
        el("td", { class: "id" }, el("a", { href: "/arm/" + encodeURIComponent(s.device), text: s.device })),
        // The labels head each cell where the table stacks on a phone (console.css).
        el("td", { text: Twin.time(s.start), "data-label": `start (${Twin.zone()})` }),
        el("td", { text: Twin.duration(s.duration_s), "data-label": "duration" }),
        el("td", { text: String(s.messages), "data-label": "messages" }),
        alarmsCell(s),
        el("td", { class: "session-status", text: s.status, "data-label": "status" }), cell);
    }));
  }

  // null: the session began before the time from which the agent holds every alarm raise, so some of its
  // raises may be gone.
  function alarmsCell(s) {
    if (s.alarms_raised !== null) return el("td", { text: String(s.alarms_raised), "data-label": "alarms raised" });
    const since = doc.alarms_known_since === null ? "the agent keeps no events"
      : `the agent holds every alarm raise from ${Twin.time(doc.alarms_known_since)}`;
    return el("td", { class: "unknown", text: "not known", title: `${since}; this session began before (docs/console.md, "Sessions")`,
      "data-label": "alarms raised" });
  }

  // A file is made on demand and can fail (history unreadable, a session that changed since the list was
  // read); a plain download link then ends in the browser's "download failed" with no reason. So the page
  // fetches the file itself and hands the browser the bytes, or shows the agent's reason.
  async function download(event, session, label) {
    event.preventDefault();
    const link = event.currentTarget;
    if (link.getAttribute("aria-busy") === "true") return;
    link.setAttribute("aria-busy", "true");
    fileResult.hidden = true;
    let response = null;
    try { response = await fetch(link.href); } catch (_) { response = null; }
    try {
      if (response && response.ok) {
        const blob = await response.blob();
        const named = /filename="?([^";]+)"?/.exec(response.headers.get("content-disposition") || "");
        const url = URL.createObjectURL(blob);
        const save = el("a", { href: url, download: named ? named[1] : "" });
        document.body.append(save);
        save.click();
        save.remove();
        setTimeout(() => URL.revokeObjectURL(url), 60000);
        return;
      }
      let payload = null;
      if (response) { try { payload = await response.json(); } catch (_) { payload = null; } }
      const result = { status: response ? response.status : 0, payload };
      fileResult.textContent = `The ${label} of ${session.device}'s session from ${Twin.time(session.start)} ` +
        `could not be made: ${Twin.refusal(result)}`;
      fileResult.hidden = false;
    } finally {
      link.removeAttribute("aria-busy");
    }
  }

  async function load() {
    try {
      doc = await Twin.getJSON("/api/sessions");
      Twin.setLink(true, "up to date");
      render();
      if (!document.body.dataset.ready) { document.body.dataset.ready = "1"; window.twinReadyAt = performance.now(); }
    } catch (_) {
      Twin.setLink(false, "agent unreachable");
    }
  }
  device.addEventListener("input", render);
  state.addEventListener("input", render);
  load();
  setInterval(load, 10000);
  // The list is read every 10 s (it comes from history), so the page learnt of an agent gone or back up to
  // 10 s late. A light stream, the events' (only new events, none at first), tells it within a second, and
  // a return reads the list again.
  let opened = false;
  const link = Twin.stream("/api/stream/events?after=" + Number.MAX_SAFE_INTEGER, { events: () => {} });
  link.addEventListener("open", () => { if (opened) load(); opened = true; });
})();
