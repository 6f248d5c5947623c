// Shared helpers of the console's pages: DOM building (text only, never HTML from data), the live stream,
// the CSRF token for requests that change state, and time formatting. No framework, no CDN.
"use strict";

const Twin = (() => {
  const body = document.body;
  const linkState = document.getElementById("link-state");

  function el(tag, attrs, ...children) {
    const node = document.createElement(tag);
    for (const [key, value] of Object.entries(attrs || {})) {
      if (value === null || value === undefined || value === false) continue;
      if (key === "class") node.className = value;
      else if (key === "text") node.textContent = value;
      else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
      else node.setAttribute(key, value === true ? "" : String(value));
    }
    for (const child of children) {
      if (child === null || child === undefined) continue;
      node.append(child instanceof Node ? child : document.createTextNode(String(child)));
    }
    return node;
  }

  // While the agent does not answer, a page keeps the last figures it was sent, and they read as current (an
  // arm ONLINE, last seen "now"); the corner's "reconnecting…" alone was easy to miss. A banner says they are
  // not live, and since when, until the agent answers again.
  const banner = el("p", { id: "link-banner", role: "alert", hidden: true });
  document.getElementById("main").before(banner);
  let downSince = null;
  // How many times the page lost the agent: a chart that drew on across a break would join the last reading
  // before it to the first after it, as if readings had come meanwhile.
  let breaks = 0;

  function setLink(live, text) {
    if (linkState) {
      linkState.className = "link " + (live ? "live" : "down");
      linkState.textContent = text;
    }
    if (live) {
      // Back after a break, the agent may be a new start with a new CSRF token: read it now, so the operator's
      // next act is most likely not refused first (a 403 in the browser's log). Best effort: an act made before
      // this read returns, or from a tab hidden through the restart, is refused once and renewed by post().
      if (downSince !== null) renewToken();
      downSince = null;
      banner.hidden = true;
      body.classList.remove("link-down");
      return;
    }
    if (downSince === null) { downSince = Date.now() / 1000; breaks += 1; }
    banner.textContent = `Out of touch with the agent since ${time(downSince)}: what this page shows is from ` +
      "then, not live. The agent may be restarting or stopped; the page reconnects by itself.";
    banner.hidden = false;
    body.classList.add("link-down");
  }

  // An EventSource that shows its state in the header; the browser reconnects by itself (retry: 1000).
  // A browser holds at most six HTTP/1.1 connections to one host, and each open stream keeps one: a seventh
  // tab of the console never loaded. So a hidden tab lets go of its stream and opens it again when shown
  // (its first frame is the whole picture; the Events and Sessions pages read theirs again on "open"). A tab
  // opened in the background connects once it is looked at. What it returns takes addEventListener, kept
  // over every new connection.
  function stream(url, handlers) {
    const listeners = [];
    let source = null;
    function connect() {
      source = new EventSource(url);
      source.onopen = () => setLink(true, "live");
      source.onerror = () => setLink(false, "reconnecting…");
      for (const [event, handler] of Object.entries(handlers)) {
        source.addEventListener(event, (message) => {
          setLink(true, "live");
          handler(JSON.parse(message.data));
        });
      }
      for (const [event, listener] of listeners) source.addEventListener(event, listener);
    }
    document.addEventListener("visibilitychange", () => {
      if (document.hidden && source) { source.close(); source = null; }
      else if (!document.hidden && !source) connect();
    });
    if (!document.hidden) connect();
    return {
      addEventListener(event, listener) {
        listeners.push([event, listener]);
        if (source) source.addEventListener(event, listener);
      },
      get connected() { return source !== null; },
    };
  }

  // Thrown for an answer that is not 2xx carries its status (and its JSON, when it has one), so a page can say
  // what the agent answered, not that it did not (`refusal`); a fetch that got no answer throws as fetch does.
  async function getJSON(url) {
    const response = await fetch(url, { headers: { Accept: "application/json" } });
    if (!response.ok) {
      const error = new Error(`${url}: ${response.status}`);
      error.status = response.status;
      error.payload = await response.json().catch(() => null);
      throw error;
    }
    return response.json();
  }

  // A select takes `value` only when it offers it (a link or an address may carry anything), else keeps its own.
  function choose(select, value) {
    if ([...select.options].some((o) => o.value === value)) select.value = value;
  }

  // A request that changes state: the server wants the page's CSRF token (the Origin is the browser's).
  // Each agent start makes a new token, so a page left open over a restart carries one the agent refuses:
  // the page reads the new one from its own document, fetched again (same origin only), and sends once more.
  // Only when that fails too does the operator see the refusal and its "reload".
  // `json`, when given, is sent as the request's JSON body.
  async function post(url, json) {
    let result = await send(url, json);
    if (result.status === 403 && result.payload && result.payload.error === "csrf_token_invalid" &&
        await renewToken()) {
      result = await send(url, json);
    }
    return result;
  }

  async function send(url, json) {
    const token = document.querySelector('meta[name="csrf-token"]').content;
    const init = { method: "POST", headers: { "X-CSRF-Token": token } };
    if (json !== undefined) {
      init.headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(json);
    }
    const response = await fetch(url, init);
    let payload = null;
    try { payload = await response.json(); } catch (_) { payload = null; }
    return { ok: response.ok, status: response.status, payload };
  }

  async function renewToken() {
    try {
      const response = await fetch(location.href, { headers: { Accept: "text/html" } });
      if (!response.ok) return false;
      const fresh = new DOMParser().parseFromString(await response.text(), "text/html")
        .querySelector('meta[name="csrf-token"]');
      if (!fresh || !fresh.content) return false;
      document.querySelector('meta[name="csrf-token"]').content = fresh.content;
      return true;
    } catch (_) {
      return false;
    }
  }

  // Why a request was not done, in the agent's words: a refusal's detail says what to do (a CSRF token that
  // could not be renewed: reload), which a bare status does not. `result` is post's, or status 0 when no
  // answer came at all.
  function refusal(result) {
    if (!result.status) return "the agent did not answer (it may be restarting); try again once the header says live";
    const p = result.payload || {};
    const why = p.detail || `the agent answered ${result.status}`;
    return `${why} (${result.status}${p.error ? ` ${p.error}` : ""})`;
  }

  // The alarm states that wait for a person (twin.core.alarms.WAITING_STATES): what the pages count and send.
  const WAITING = new Set(["ACTIVE", "LATCHED"]);

  // Several alarms acknowledged at once (an arm's, or the Fleet page's shown): POST /alarms/ack with their
  // ids, ACK_MANY_MAX a request (twin.service.shards), which the agent makes in one go and keeps with one
  // write of its state file; one POST per alarm, each waiting for that write, took minutes for a few hundred,
  // and logged a 409 for each already cleared. The answer says each id's outcome (each recorded as its own
  // event, as a single click's). A request the agent finds too large (413: a small [http] max_body_bytes,
  // long ids) goes again as two halves. Only the ids the operator confirmed are sent: one raised meanwhile
  // waits for its own look. A refusal of the page itself (403: a token that could not be renewed; no answer
  // at all) ends the run: that request's ids counted refused, the rest unsent.
  const ACK_MANY_MAX = 1000;

  // A run cut short by a reload (or by leaving the page) ended without a word, its later chunks never sent.
  // It is kept in the tab's sessionStorage while it runs, so the page, opened again, says how many had no
  // answer (interruptedAck) and the operator can press again.
  // One record a page (its path): an arm's Acknowledge all, run after a Fleet run was cut short by following
  // a link, wrote over the Fleet page's record and removed it on its end (a review).
  const ACK_RUN = `twin.ack.run:${location.pathname}`;
  // A reload aborts the request in flight, and the run then ends as if that request were answered: the record
  // stays as it was before, or the page opened again has nothing (or too little) to say.
  let leaving = false;
  window.addEventListener("pagehide", () => { leaving = true; });
  // A link followed (not a reload) may abort the request before pagehide: beforeunload comes first.
  window.addEventListener("beforeunload", () => { leaving = true; });
  window.addEventListener("pageshow", () => { leaving = false; });  // back from the browser's page cache

  function keepRun(total, answered) {
    if (leaving) return;
    try {
      if (total === null) sessionStorage.removeItem(ACK_RUN);
      else {
        const run = { path: location.pathname, total, answered, at: Date.now() / 1000 };
        sessionStorage.setItem(ACK_RUN, JSON.stringify(run));
      }
    } catch (_) { /* no storage (a browser's setting): the page only cannot say it after a reload */ }
  }

  // The run this page (its path) left unfinished, once: {total, answered, at}, else null. Another page's
  // is left for that page (an arm's link followed mid-way must not swallow the Fleet page's).
  function interruptedAck() {
    try {
      const run = JSON.parse(sessionStorage.getItem(ACK_RUN) || "null");
      if (!run || run.path !== location.pathname) return null;
      sessionStorage.removeItem(ACK_RUN);
      return run;
    } catch (_) {
      return null;
    }
  }

  // What a page says of it: how many of the alarms had no answer, and to press `button` again.
  function interruptedText(run, button) {
    const left = run.total - run.answered;
    return `An acknowledgement of ${run.total} alarm${run.total === 1 ? "" : "s"} begun at ${time(run.at)} ` +
      `(${zone()}) was cut short by a reload or by leaving the page: ` +
      `${left} of them ${left === 1 ? "was" : "were"} not sent or had no answer. Press ${button} again for ` +
      "the rest (one done meanwhile counts as already acknowledged).";
  }

  async function acknowledgeMany(alarms, progress) {
    const tally = { acknowledged: 0, reset: 0, ACKNOWLEDGED: 0, NORMAL: 0, gone: 0, notKept: 0, refused: 0,
      unsent: 0, why: "" };
    const ids = alarms.map((a) => a.alarm_id);
    keepRun(ids.length, 0);
    try {
      await sendChunks(ids, tally, progress);
    } finally {
      keepRun(null);
    }
    return tally;
  }

  async function sendChunks(ids, tally, progress) {
    const pending = [];
    for (let i = 0; i < ids.length; i += ACK_MANY_MAX) pending.push(ids.slice(i, i + ACK_MANY_MAX));
    let done = 0;
    while (pending.length) {
      const chunk = pending.shift();
      if (progress) progress(done, ids.length);
      let result;
      try {
        result = await post("/alarms/ack", chunk);
      } catch (_) {
        result = { ok: false, status: 0, payload: null };
      }
      const p = result.payload || {};
      if (result.status === 413 && chunk.length > 1) {
        const half = Math.ceil(chunk.length / 2);
        pending.unshift(chunk.slice(0, half), chunk.slice(half));
        continue;
      }
      done += chunk.length;
      keepRun(ids.length, done);
      if (Array.isArray(p.results)) {
        const notKept = result.status === 503 && p.error === "not_saved";
        if (notKept && !tally.why) tally.why = refusal(result);
        for (const r of p.results) countOutcome(tally, r, notKept);
        continue;
      }
      if (!tally.why) tally.why = refusal(result);
      tally.refused += chunk.length;
      if (!result.status || result.status === 403) {
        tally.unsent = pending.reduce((n, c) => n + c.length, 0);
        break;
      }
    }
  }

  function countOutcome(tally, r, notKept) {
    if (r.outcome === "acknowledged") {
      if (notKept) tally.notKept += 1;
      else tally[r.state === "NORMAL" ? "reset" : "acknowledged"] += 1;
    } else if (r.outcome === "nothing_to_acknowledge" && (r.state === "ACKNOWLEDGED" || r.state === "NORMAL")) {
      tally[r.state] += 1;
    } else if (r.outcome === "alarm_not_found") {
      tally.gone += 1;
    } else {
      tally.refused += 1;
      if (!tally.why) tally.why = r.detail || r.outcome;
    }
  }

  // "7 acknowledged, 1 already cleared": each outcome counted, the first refusal in the agent's words.
  function tallyText(t) {
    const parts = [[t.acknowledged, "acknowledged"], [t.reset, "reset (it had cleared)"],
      [t.ACKNOWLEDGED, "already acknowledged"], [t.NORMAL, "already cleared"],
      [t.gone, "gone (its arm forgotten)"], [t.notKept, "acknowledged but not kept"],
      [t.refused, "refused"], [t.unsent, "not sent"]].filter(([n]) => n).map(([n, what]) => `${n} ${what}`);
    return (parts.length ? parts.join(", ") : "nothing to acknowledge") + (t.why ? `: ${t.why}` : "");
  }

  function tallyOk(t) { return !t.refused && !t.notKept; }

  function ago(epoch, now) {
    if (epoch === null || epoch === undefined) return "never";
    const s = Math.max(0, now - epoch);
    if (s < 1) return "now";
    if (s < 90) return `${Math.round(s)} s ago`;
    if (s < 5400) return `${Math.round(s / 60)} min ago`;
    if (s < 172800) return `${Math.round(s / 3600)} h ago`;
    return `${Math.round(s / 86400)} d ago`;
  }

  function time(epoch) {
    if (epoch === null || epoch === undefined) return "";
    const d = new Date(epoch * 1000);
    const pad = (n, w = 2) => String(n).padStart(w, "0");
    return `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ` +
      `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
  }

  // The pages show times in the browser's zone, the exports and plots in UTC: each table says which zone
  // its times are in, so a time read off the page matches the export's after the offset.
  function zone() {
    const minutes = -new Date().getTimezoneOffset(), abs = Math.abs(minutes);
    const hm = `${String(Math.floor(abs / 60)).padStart(2, "0")}:${String(abs % 60).padStart(2, "0")}`;
    return minutes === 0 ? "UTC" : `UTC${minutes < 0 ? "-" : "+"}${hm}`;
  }

  function duration(seconds) {
    const s = Math.round(seconds);
    if (s < 120) return `${s} s`;
    if (s < 7200) return `${Math.floor(s / 60)} min ${s % 60} s`;
    return `${Math.floor(s / 3600)} h ${Math.round((s % 3600) / 60)} min`;
  }

  function num(value, digits) {
    return value === null || value === undefined ? "–" : Number(value).toFixed(digits);
  }

  const page = body.dataset.page;
  for (const a of document.querySelectorAll("[data-nav]")) {
    if (a.dataset.nav === page || (page === "arm" && a.dataset.nav === "fleet")) a.classList.add("active");
  }

  return { el, stream, getJSON, choose, post, refusal, WAITING, acknowledgeMany, tallyText, tallyOk, ago, time, zone, duration, num, setLink, breaks: () => breaks,
    interruptedAck, interruptedText,
    main: document.getElementById("main"),
    device: body.dataset.device, rerun: body.dataset.rerun };
})();
