// The twin's events: filters by device, level, kind, text and time range; a live tail with auto-scroll; and
// the same selection exported as CSV or JSON (cells a spreadsheet would run as formulas are neutralised).
"use strict";

(() => {
  const { el, main } = Twin;
  const MAX_ROWS = 5000;
  // The most events /api/events answers at once (the agent's own cap, whatever `limit` asks): a load that
  // fills it is the selection's newest, not all of it. A walk read "1000 events" of a selection of 11,000.
  const LOAD_MAX = 1000;
  const RETRY_MAX_S = 30;
  const device = el("input", { type: "search", placeholder: "device", "aria-label": "device" });
  // The box finds part of an id, as on the Fleet and Sessions pages; ticked, one arm's whole id (an arm
  // page's link to its events ticks it: arm-1's must not bring arm-10's).
  const whole = el("input", { type: "checkbox", id: "device-whole", "aria-label": "whole id" });
  const level = el("select", { "aria-label": "level" }, el("option", { value: "", text: "any level" }),
    el("option", { value: "warning", text: "warning and worse" }), el("option", { value: "error", text: "errors" }));
  const kind = el("select", { "aria-label": "kind" }, el("option", { value: "", text: "any kind" }),
    ...["status", "alarm", "rejected", "broker", "worker", "twin", "calibration", "agent"].map((k) => el("option", { value: k, text: k })));
  const text = el("input", { type: "search", placeholder: "text", "aria-label": "text" });
  const since = el("input", { type: "datetime-local", "aria-label": "from", step: "1" });
  const until = el("input", { type: "datetime-local", "aria-label": "until", step: "1" });
  const follow = el("input", { type: "checkbox", id: "follow", checked: true });
  const csv = el("a", { id: "export-csv", text: "CSV", download: "" });
  const json = el("a", { id: "export-json", text: "JSON", download: "" });
  const count = el("span", { class: "counts" });
  const body = el("tbody");
  const box = el("div", { class: "events panel" },
    el("table", { id: "events" }, el("thead", {}, el("tr", {}, ...[`time (${Twin.zone()})`, "level", "kind", "device", "event"].map((t) => el("th", { text: t })))), body));
  main.append(el("h1", { text: "Events" }),
    el("div", { class: "toolbar" }, device, el("label", {}, whole, " whole id"), level, kind, text, "from", since, "until", until,
      el("label", {}, follow, " auto-scroll"), "export:", csv, json, count), box);

  let events = [], lastId = 0, loadedAll = true;

  function showCount() {
    count.textContent = `${events.length} event${events.length === 1 ? "" : "s"}` + (loadedAll ? ""
      : ` (the selection's newest ${LOAD_MAX} when loaded, and those since: narrow it, or export it for all)`);
  }

  function params(extra) {
    const p = new URLSearchParams();
    if (device.value.trim()) p.set(whole.checked ? "device" : "device_part", device.value.trim());
    if (level.value) p.set("level", level.value);
    if (kind.value) p.set("kind", kind.value);
    if (text.value.trim()) p.set("q", text.value.trim());
    if (since.value) p.set("since", String(new Date(since.value).getTime() / 1000));
    if (until.value) p.set("until", String(new Date(until.value).getTime() / 1000));
    for (const [k, v] of Object.entries(extra || {})) p.set(k, v);
    return p.toString();
  }

  const LEVELS = { info: 20, warning: 30, error: 40 };
  function matches(e) {
    const q = text.value.trim().toLowerCase(), d = device.value.trim();
    if (d && (whole.checked ? e.device !== d : !e.device.toLowerCase().includes(d.toLowerCase()))) return false;
    if (level.value && (LEVELS[e.level] || 20) < LEVELS[level.value]) return false;
    if (kind.value && e.kind !== kind.value) return false;
    if (q && !e.message.toLowerCase().includes(q) && !e.device.toLowerCase().includes(q)) return false;
    if (since.value && e.time < new Date(since.value).getTime() / 1000) return false;
    if (until.value && e.time >= new Date(until.value).getTime() / 1000) return false;
    return true;
  }

  function row(e) {
    return el("tr", { "data-id": e.id, class: "level-" + e.level },
      el("td", { text: Twin.time(e.time) }), el("td", { text: e.level }), el("td", { text: e.kind }),
      el("td", { class: "id" }, e.device ? el("a", { href: "/arm/" + encodeURIComponent(e.device), text: e.device }) : ""),
      el("td", { class: "msg", text: e.message }));
  }

  // A loaded selection with no event says so in the table, and what the device box wants (an exact id).
  const NONE = "no event matches these filters (the device box finds part of an arm's id, or with whole id " +
    "ticked one arm's whole id, e.g. arm-001)";
  const none = el("tr", { id: "events-none" }, el("td", { colspan: 5, class: "empty", text: NONE }));

  function render(loaded = true) {
    body.replaceChildren(...(events.length || !loaded ? events.map(row) : [none]));
    showCount();
    if (follow.checked) box.scrollTop = box.scrollHeight;
  }

  function append(fresh) {
    const add = fresh.filter((e) => e.id > lastId && matches(e));
    for (const e of fresh) lastId = Math.max(lastId, e.id);
    if (!add.length) return;
    none.remove();
    events.push(...add);
    const rows = add.map(row);
    body.append(...rows);
    while (events.length > MAX_ROWS) { events.shift(); body.firstChild.remove(); }
    showCount();
    if (follow.checked) box.scrollTop = box.scrollHeight;
  }

  // A load that fails (the agent busy or restarting) is tried again, sooner first, until one succeeds or
  // the selection changes; meanwhile the table is emptied, since its rows were chosen by the filters before.
  // Only the newest load may fill the table: an older one that answers late would show another selection.
  let source = null, loads = 0, retry = null, failures = 0;
  async function load() {
    const mine = ++loads;
    clearTimeout(retry);
    csv.href = "/api/events.csv?" + params();
    json.href = "/api/events.json?" + params();
    // Ends swapped: the agent refuses the range (400); said here, not as an agent out of reach.
    if (since.value && until.value && new Date(until.value) <= new Date(since.value)) {
      events = [];
      loadedAll = true;
      render(false);
      count.textContent = "the until time is not after the from time: nothing lies between them";
      return;
    }
    try {
      const doc = await Twin.getJSON("/api/events?" + params({ limit: String(LOAD_MAX) }));
      if (mine !== loads) return;
      failures = 0;
      events = doc.events;
      // A whole id the agent holds no event of at all (the agent's `detail` says so): a slip of the id, more
      // likely than filters too narrow.
      none.firstChild.textContent = doc.detail ? `no event matches: the agent holds no event of ` +
        `"${device.value.trim()}" at all. Check the id against the Fleet page: with whole id ticked the ` +
        "box wants one arm's whole id, in its case, e.g. arm-001" : NONE;
      // The agent says whether the selection holds more than it answered: a selection of exactly LOAD_MAX
      // is all of it.
      loadedAll = !doc.more;
      lastId = Math.max(lastId, doc.last_id);
      render();
      if (!document.body.dataset.ready) { document.body.dataset.ready = "1"; window.twinReadyAt = performance.now(); }
    } catch (_) {
      if (mine !== loads) return;
      const wait = Math.min(RETRY_MAX_S, 2 ** failures);
      failures += 1;
      events = [];
      loadedAll = true;
      render(false);
      count.textContent = `could not load the events; trying again in ${wait} s`;
      Twin.setLink(false, "agent unreachable");
      retry = setTimeout(load, wait * 1000);
    } finally {
      if (source === null) {
        source = Twin.stream("/api/stream/events?after=" + lastId, { events: append });
        source.addEventListener("open", reconnected);
      }
    }
  }

  // The stream came back after a break: the agent may have restarted, and a new agent numbers its events
  // from 1 again, so every one of them would be at or under the last id this page saw and `append` would
  // drop them all while the header says live. The selection is loaded afresh, its ids counted from nothing;
  // the old rows go at once, or the new agent's first events, streamed before the load answers, would be
  // shown below the old agent's as if one list.
  let opened = false;
  function reconnected() {
    if (!opened) { opened = true; return; }  // the first connection: load() has just read the selection
    lastId = 0;
    events = [];
    loadedAll = true;
    render(false);
    count.textContent = "the agent is back: loading its events…";
    load();
  }
  let timer = null;
  for (const input of [device, whole, level, kind, text, since, until]) {
    input.addEventListener("input", () => { clearTimeout(timer); timer = setTimeout(load, 250); });
  }
  follow.addEventListener("change", () => { if (follow.checked) box.scrollTop = box.scrollHeight; });
  // A link may choose the selection (an arm page's "its events": /events?device=arm-001): its device,
  // level, kind and text, as the API names them. A value the lists do not offer is left out.
  const asked = new URLSearchParams(location.search);
  device.value = asked.get("device") || asked.get("device_part") || "";
  whole.checked = asked.has("device");
  text.value = asked.get("q") || "";
  for (const [select, key] of [[level, "level"], [kind, "kind"]]) Twin.choose(select, asked.get(key) || "");
  load();
})();
