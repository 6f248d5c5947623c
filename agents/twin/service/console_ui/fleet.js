// The fleet: every arm as a card (grid) or a row (list), filtered by status and alarm, searched by id, live.
// Only what is on screen is in the DOM (a virtualised viewport), so 2,000 arms cost what 50 do.
"use strict";

(() => {
  const { el, main } = Twin;
  // CARD_W is a card's least width: a row's cards share out what is left, so no band of the window stays empty.
  const CARD_W = 230, CARD_H = 138, GAP = 8, ROW_H = 30, PHONE_ROW_H = 44;
  // A phone's list rows are two lines tall (console.css's query of the same width), so a cell wraps: in one
  // line at 390 px every id read "arm-00…" and every alarm "critical over_…".
  const PHONE = window.matchMedia("(max-width: 700px)");
  let rowH = ROW_H;
  let columns = {}, rows = [], shown = [], now = Date.now() / 1000, listening = null;
  // The arms held by a refused calibration (the document's "held"): no card, yet their alarms are raised.
  let held = [];
  // Until the agent's first document arrives the page knows nothing of the fleet: it must not say that no
  // arm has been heard from (a slow first answer showed that bare line to a new user).
  let loaded = false;
  let mode = localStorage.getItem("twin.fleet.view") === "list" ? "list" : "grid";

  const search = el("input", { type: "search", placeholder: "search arm id", "aria-label": "search by id" });
  const status = el("select", { "aria-label": "status" },
    el("option", { value: "", text: "any status" }), el("option", { value: "ONLINE", text: "ONLINE" }),
    el("option", { value: "STALE", text: "STALE" }), el("option", { value: "OFFLINE", text: "OFFLINE" }));
  const alarm = el("select", { "aria-label": "alarm" },
    el("option", { value: "", text: "any alarm state" }), el("option", { value: "any", text: "with an alarm" }),
    el("option", { value: "critical", text: "critical" }), el("option", { value: "warning", text: "warning" }),
    el("option", { value: "waiting", text: "unacknowledged" }), el("option", { value: "none", text: "no alarm" }));
  const sort = el("select", { "aria-label": "sort" },
    el("option", { value: "id", text: "sort: id" }), el("option", { value: "alarm", text: "sort: worst alarm" }),
    el("option", { value: "hot", text: "sort: hottest servo" }), el("option", { value: "loss", text: "sort: loss" }));
  const gridButton = el("button", { type: "button", text: "Grid", onclick: () => setMode("grid") });
  const listButton = el("button", { type: "button", text: "List", onclick: () => setMode("list") });
  const counts = el("span", { class: "counts" });
  // Every alarm waiting for a person on the arms the filters show (all of them, not only those scrolled to):
  // ten hot arms took twenty clicks one by one. Its answer goes under the toolbar (Twin.acknowledgeMany).
  const ackShown = el("button", { type: "button", id: "ack-shown", disabled: true, text: "Acknowledge shown (0)" });
  const ackResult = el("p", { id: "fleet-ack-result", role: "status", hidden: true });
  let ackBusy = false;
  // An acknowledgement this page began and a reload cut short: said at once, or its unsent ids go unnoticed.
  const cut = Twin.interruptedAck();
  if (cut) {
    ackResult.hidden = false;
    ackResult.className = "ack-refused";
    ackResult.textContent = Twin.interruptedText(cut, '"Acknowledge shown"');
  }
  // What no card can show: a subscription the broker refuses, whose arms are never heard.
  const notices = el("div", { class: "notices", id: "fleet-notices", role: "alert" });
  notices.hidden = true;
  const viewport = el("div", { class: "viewport", id: "fleet-view", role: "list" });
  const spacer = el("div", { class: "spacer" });
  viewport.append(spacer);
  main.append(
    notices,
    el("div", { class: "toolbar" }, search, status, alarm, sort,
      el("span", { class: "toggle" }, gridButton, listButton), ackShown, counts),
    ackResult,
    viewport);

  function setMode(next) {
    mode = next;
    localStorage.setItem("twin.fleet.view", mode);
    gridButton.classList.toggle("on", mode === "grid");
    listButton.classList.toggle("on", mode === "list");
    viewport.scrollTop = 0;
    render();
  }

  const SEVERITY = { critical: 2, warning: 1 };
  // Whether the filters let an arm through; a held arm has no status (null), so none passes a status filter.
  function passes(device, st, sev, waiting) {
    const q = search.value.trim().toLowerCase(), al = alarm.value;
    if (q && !device.toLowerCase().includes(q)) return false;
    if (status.value && st !== status.value) return false;
    if (al === "any" && !sev) return false;
    if (al === "none" && sev) return false;
    if ((al === "critical" || al === "warning") && sev !== al) return false;
    // Any alarm of the arm waiting for a person (ACTIVE, or LATCHED: cleared, unseen), not only its worst.
    if (al === "waiting" && !(waiting > 0)) return false;
    return true;
  }
  function filter() {
    const c = columns;
    shown = rows.filter((r) => passes(r[c.device], r[c.status], r[c.alarm_severity], r[c.unacknowledged]));
    const key = sort.value;
    if (key === "alarm") shown.sort((a, b) => alarmRank(b) - alarmRank(a));
    else if (key === "hot") shown.sort((a, b) => (b[c.hot_c] ?? -1e9) - (a[c.hot_c] ?? -1e9));
    else if (key === "loss") shown.sort((a, b) => (b[c.loss_pct] ?? 0) - (a[c.loss_pct] ?? 0));
  }

  // Worst first: by severity, and within one the arms whose alarm shown waits for a person (ACTIVE, LATCHED)
  // before those whose alarm shown is acknowledged, then those with another alarm waiting behind it. By
  // severity alone, a walk's acknowledged criticals sat among (and above) the ones nobody had seen.
  function alarmRank(r) {
    const c = columns;
    return 4 * (SEVERITY[r[c.alarm_severity]] || 0) + (r[c.alarm_severity] && WAITING.has(r[c.alarm_state]) ? 2 : 0) +
      (r[c.unacknowledged] > 0 ? 1 : 0);
  }

  // The worst alarm is the one shown; others may wait for someone while it does not (a critical one
  // acknowledged, a warning still ACTIVE), and the arm would read as dealt with.
  const { WAITING } = Twin;
  function othersWaiting(r) {
    const c = columns, others = (r[c.unacknowledged] || 0) - (WAITING.has(r[c.alarm_state]) ? 1 : 0);
    return others > 0 ? [" · ", el("span", { class: "waiting", title: "alarms not acknowledged besides the one shown: the arm's page lists them",
      text: `+${others} unacknowledged` })] : [];
  }

  // A row gives the worst alarm one column and its state, with the alarms waiting behind it, the next: in one
  // column at 1280 px the state and "+2 unacknowledged" were cut off behind the kind. Each cell's title holds
  // its whole text for a narrower window.
  function alarmCell(r) {
    const c = columns, sev = r[c.alarm_severity];
    if (!sev) return el("span", { class: "muted", text: "no alarm" });
    const what = `${r[c.alarm_kind]} (${r[c.alarm_joint]})`;
    // The severity's word goes on a phone (its colour stays, and the counts above name it), and the kind is
    // said short ("overheating shoulder lift"): its two lines of about 100 px cut "over_temperature_critical (shoulder_lift)" to "over_tempe
    // / rature_cri…", and broken only after its "_" it took four. The title keeps the whole name.
    const shown = PHONE.matches ? `${PHONE_KINDS[r[c.alarm_kind]] || spaced(r[c.alarm_kind])} ${spaced(r[c.alarm_joint])}` : what;
    return el("span", { class: "sev-" + sev, title: `${sev} ${what}` }, el("span", { class: "sev-word", text: sev + " " }), shown);
  }

  // A phone's words for an alarm's kind: its severity (warning, critical) is the cell's colour there.
  const PHONE_KINDS = { over_temperature: "overheating", over_temperature_critical: "overheating",
    over_current: "over current", servo_error: "servo error" };
  function spaced(name) { return String(name).replaceAll("_", " "); }

  function stateCell(r) {
    const c = columns, state = r[c.alarm_severity] ? r[c.alarm_state] : "";
    const waiting = othersWaiting(r), node = el("span", {}, state, ...(state ? waiting : waiting.slice(1)));
    node.title = node.textContent;
    return node;
  }

  // A card gives the alarm's severity and joint one line, its kind the next, its state the next and the
  // alarms waiting behind it one more: after a kind such as over_temperature_critical a card cut "+5
  // unacknowledged" to "+5 u…", and "critical · shoulder_lift · ACKNOWLEDGED" to "… · ACKNOWL…".
  function cardAlarm(r) {
    const c = columns, sev = r[c.alarm_severity];
    if (!sev) return [el("div", { class: "line muted", text: "no alarm" })];
    const waiting = othersWaiting(r).slice(1);
    return [el("div", { class: "line" }, el("span", { class: "sev-" + sev, text: sev }), ` · ${r[c.alarm_joint]}`),
      el("div", { class: "line", text: r[c.alarm_kind] }), el("div", { class: "line alarm-state", text: r[c.alarm_state] }),
      ...(waiting.length ? [el("div", { class: "line" }, ...waiting)] : [])];
  }

  // On a card the temperature comes before the servo's name, and a silent arm's "then" (when it was last
  // heard, on its status line) before both: an old reading must not read as now. "hottest, last heard: 45 C
  // (shoulder_lift)" was wider than a 230 px card, which cut the servo's name.
  function cardHot(r) {
    const c = columns;
    if (r[c.hot_c] === null) return "hottest: –";
    const when = r[c.status] === "ONLINE" ? "hottest: " : "hottest then: ";
    return `${when}${Twin.num(r[c.hot_c], 0)} C (${r[c.hot_joint]})`;
  }

  // "C", as the alarms' values and messages, the e-mails and the docs write it: the page said "45 °C" beside
  // an alarm's "at 64 C".
  function hotText(r) {
    const c = columns;
    if (r[c.hot_c] === null) return "–";
    return `${r[c.hot_joint]} ${Twin.num(r[c.hot_c], 0)} C`;
  }

  // Its title holds its whole text, as the alarm's does: a tablet's column may cut a long servo name.
  function hotCell(r) {
    const c = columns;
    const text = hotText(r) + (r[c.status] === "ONLINE" || r[c.hot_c] === null ? "" : " when last heard");
    return el("span", { class: "wide", title: text, text });
  }

  // Its worker process is being started again, or the agent is stopping: the row is the worker's last
  // checkpoint.
  const MIRROR_NOTES = {
    restarting: "its worker is being started again: figures from its last checkpoint",
    stopping: "the agent is stopping: figures from its worker's last checkpoint",
  };
  function restarting(r) {
    const mirror = r[columns.mirror], title = MIRROR_NOTES[mirror];
    return title ? [" ", el("span", { class: "restarting", title, text: mirror })] : [];
  }

  // An arm with no calibration of its own, or whose newest file in the store was refused (it keeps the one
  // it had): the card said nothing of the second, and the file someone just pushed was not in force.
  // Both at once is an arm held: its file refused with none to keep, its messages refused (not the nominal).
  const CALIBRATION_MARKS = {
    uncalibrated: "no LeRobot calibration: its page says how to push one",
    "file refused": "its newest calibration file is refused; it keeps the one it had: its page says why",
    held: "its calibration file is refused and it has none to keep: its twin holds still; its page says why",
  };
  function calibrationWord(r) {
    const none = r[columns.uncalibrated], refused = r[columns.calibration_refused];
    return none && refused ? "held" : none ? "uncalibrated" : refused ? "file refused" : "";
  }
  // When the arm was last heard from; for a held arm, that it is held and whether its messages come: its
  // card read "OFFLINE · never" whether it published (every message refused) or was off, and the word
  // "held" beside a long id was cut with it.
  function lastSeen(r) {
    const c = columns, seen = Twin.ago(r[c.last_seen], now);
    if (calibrationWord(r) !== "held") return seen;
    // Short enough for a card of the least width: "STALE · held: 12345 refused".
    const held = r[c.rejected] ? `held: ${r[c.rejected]} refused` : "held: none heard";
    return r[c.last_seen] === null ? held : `${seen}, ${held}`;
  }
  function calibrationMark(r) {
    const word = calibrationWord(r);
    return word ? [" ", el("span", { class: "uncalibrated", title: CALIBRATION_MARKS[word], text: word })] : [];
  }

  // A rate not known reads "– Hz", which said nothing of why: its title does. Only a restarting worker's
  // checkpoint leaves it unknown (a live mirror's meter always gives a number).
  const RATE_UNKNOWN = "rate not known yet: its worker was started again";
  function rateTitle(r) { return r[columns.rate_hz] == null ? RATE_UNKNOWN : null; }

  function card(r, x, y, w) {
    const c = columns, id = r[c.device];
    const critical = r[c.alarm_severity] === "critical" ? " critical" : "";
    const node = el("a", { class: "card " + r[c.status] + critical, href: "/arm/" + encodeURIComponent(id), role: "listitem",
      "data-device": id },
      // Its title: an id longer than the card is cut, and read whole on hover.
      el("div", { class: "id", title: id }, id, ...calibrationMark(r)),
      // "restarting" or "stopping" beside the status it qualifies: after the id and "uncalibrated" a card cut it.
      el("div", { class: "line" }, el("span", { class: "status " + r[c.status], text: r[c.status] }),
        " · " + lastSeen(r), ...restarting(r).map((n) => (n === " " ? " · " : n))),
      el("div", { class: "line", title: rateTitle(r),
        text: `${Twin.num(r[c.rate_hz], 1)} Hz · loss ${Twin.num(r[c.loss_pct], 1)} %` }),
      el("div", { class: "line", text: cardHot(r) }),
      ...cardAlarm(r));
    node.style.transform = `translate(${x}px, ${y}px)`;
    node.style.width = w + "px";
    node.style.height = CARD_H + "px";
    return node;
  }

  function listRow(r, y) {
    const c = columns, id = r[c.device];
    const word = calibrationWord(r), name = id + (word ? ` (${word})` : "");
    const node = el("a", { class: "row", href: "/arm/" + encodeURIComponent(id), role: "listitem", "data-device": id },
      el("span", { text: name, title: name, class: "arm-id" + (word ? " uncalibrated" : "") }, ...restarting(r)),
      el("span", { class: "status " + r[c.status], text: r[c.status] }),
      el("span", { class: "wide", text: lastSeen(r) }),
      el("span", { class: "wide minor", title: rateTitle(r), text: Twin.num(r[c.rate_hz], 1) + " Hz" }),
      el("span", { class: "wide minor", text: Twin.num(r[c.loss_pct], 1) + " %" }),
      alarmCell(r), stateCell(r),
      hotCell(r));
    node.style.top = y + "px";
    node.style.height = rowH + "px";
    return node;
  }

  function header() {
    const node = el("div", { class: "row head" }, el("span", { text: "arm" }), el("span", { text: "status" }),
      el("span", { class: "wide", text: "last seen" }), el("span", { class: "wide minor", text: "rate" }),
      el("span", { class: "wide minor", text: "loss" }), el("span", { text: "worst alarm" }), el("span", { text: "its state" }),
      el("span", { class: "wide", text: "hottest servo" }));
    node.style.height = rowH + "px";
    return node;
  }

  // The held arms the filters let through: their links show their alarms waiting, as a card does its own.
  function heldShown() {
    return held.filter((h) => passes(h.device, null, h.alarm_severity, h.unacknowledged));
  }

  function showAckShown() {
    const n = shown.reduce((sum, r) => sum + (r[columns.unacknowledged] || 0), 0) +
      heldShown().reduce((sum, h) => sum + h.unacknowledged, 0);
    const text = `Acknowledge shown (${n})`;
    if (ackShown.textContent !== text) ackShown.textContent = text;
    ackShown.disabled = ackBusy || n === 0;
  }

  // What the confirmation adds of the held arms shown, whose alarms would otherwise be taken unannounced.
  function heldText(alarms, heldDevices) {
    const mine = alarms.filter((a) => heldDevices.has(a.device));
    const names = [...new Set(mine.map((a) => a.device))];
    if (!names.length) return "";
    const more = names.length > HELD_SHOWN ? ` and ${names.length - HELD_SHOWN} more` : "";
    return `, ${mine.length} of them of the held arm${plural(names.length)} ` +
      `${names.slice(0, HELD_SHOWN).join(", ")}${more} (no card: linked above)`;
  }

  // The ids are read from /alarms once the operator asks, for the arms shown then (with the held arms the
  // filters let through); the confirmation says how many of how many arms, and only those are sent.
  async function acknowledgeShown() {
    const heldDevices = new Set(heldShown().filter((h) => h.unacknowledged > 0).map((h) => h.device));
    const devices = new Set(shown.filter((r) => r[columns.unacknowledged] > 0).map((r) => r[columns.device]));
    for (const device of heldDevices) devices.add(device);
    let alarms;
    try {
      alarms = (await Twin.getJSON("/alarms")).alarms.filter((a) => devices.has(a.device) && WAITING.has(a.state));
    } catch (error) {
      ackResult.hidden = false;
      ackResult.className = "ack-refused";
      // The same words as an act refused or without an answer: without one the page goes on showing what it
      // had, so say when to try again rather than leave a failure that reads as current once the agent is back.
      ackResult.textContent = "the alarms could not be read: " +
        Twin.refusal({ status: error.status || 0, payload: error.payload });
      return;
    }
    const arms = new Set(alarms.map((a) => a.device)).size;
    if (!alarms.length) { ackResult.hidden = false; ackResult.className = "ack-ok"; ackResult.textContent = "nothing to acknowledge"; return; }
    if (!window.confirm(`Acknowledge ${alarms.length} alarm${alarms.length === 1 ? "" : "s"} of the ${arms} ` +
      `arm${arms === 1 ? "" : "s"} shown (ACTIVE or LATCHED)${heldText(alarms, heldDevices)}? Each is ` +
      "acknowledged as from its arm's page.")) return;
    ackBusy = true;
    showAckShown();
    ackResult.hidden = false;
    ackResult.className = "";
    const tally = await Twin.acknowledgeMany(alarms, (i, n) => { ackResult.textContent = `acknowledging ${n}${i ? ` (${i} done)` : ""}…`; });
    ackBusy = false;
    showAckShown();
    ackResult.className = Twin.tallyOk(tally) ? "ack-ok" : "ack-refused";
    ackResult.textContent = `${arms} arm${arms === 1 ? "" : "s"}: ${Twin.tallyText(tally)}`;
  }
  ackShown.addEventListener("click", acknowledgeShown);

  function render() {
    showAckShown();
    const width = viewport.clientWidth - 2 * GAP, top = viewport.scrollTop, height = viewport.clientHeight;
    const nodes = [];
    if (mode === "grid") {
      const perRow = Math.max(1, Math.floor((width + GAP) / (CARD_W + GAP)));
      const cardW = Math.max(CARD_W, Math.floor((width + GAP) / perRow) - GAP);
      const lines = Math.ceil(shown.length / perRow);
      spacer.style.height = lines * (CARD_H + GAP) + GAP + "px";
      const first = Math.max(0, Math.floor(top / (CARD_H + GAP)) - 1);
      const last = Math.min(lines, Math.ceil((top + height) / (CARD_H + GAP)) + 1);
      for (let line = first; line < last; line++) {
        for (let k = 0; k < perRow; k++) {
          const r = shown[line * perRow + k];
          if (r) nodes.push(card(r, GAP + k * (cardW + GAP), GAP + line * (CARD_H + GAP), cardW));
        }
      }
    } else {
      rowH = PHONE.matches ? PHONE_ROW_H : ROW_H;
      nodes.push(header());
      spacer.style.height = (shown.length + 1) * rowH + "px";
      const first = Math.max(0, Math.floor(top / rowH) - 2);
      const last = Math.min(shown.length, Math.ceil((top + height) / rowH) + 2);
      for (let i = first; i < last; i++) nodes.push(listRow(shown[i], (i + 1) * rowH));
    }
    if (!shown.length) {
      const text = !loaded ? "loading the fleet…" : rows.length ? "no arm matches the filters" : unheard();
      nodes.push(el("div", { class: "empty", id: "fleet-empty", "data-loaded": String(loaded), text }));
    }
    spacer.replaceChildren(...nodes);
  }

  // The page a new user first sees is often empty: say what the agent listens on and what to check.
  function unheard() {
    // A notice may name arms whose messages come and are refused: "none heard" would contradict it. But no
    // notice says the broker is down (an arm held by its calibration is named without one): that comes first.
    const down = listening && listening.stopping ? "the agent is stopping" :
      "the agent is not connected to its broker (GET /healthz says why)";
    if (!notices.hidden) {
      if (listening && !listening.connected) return `no arm has a twin yet: ${down}; the notices above say more`;
      return "no arm has a twin yet: the notices above say why";
    }
    const said = "no arm has been heard from yet";
    if (!listening) return said;
    if (!listening.connected) return `${said}: ${down}`;
    return `${said}. The agent listens on ${listening.filters.join(", ")}. If your arms publish and none ` +
      "appears (nor a notice above naming it), check that they publish on that topic, and that the " +
      "agent's identity may receive it: " +
      "IoT Core drops, without a word, what an identity may not iot:Receive (docs/agent.md, IAM permissions).";
  }

  // An arm held by its refused calibration has no card, yet its servos' alarms are raised: each one is
  // linked to its page, which lists them to acknowledge. Every one, from the document's list (the notices
  // name five and count the rest); past five folded, as the notices are, kept open across updates.
  const HELD_SHOWN = 5;
  function plural(n) { return n === 1 ? "" : "s"; }
  // "none heard" for one that has sent nothing since the agent started: an arm publishing with no twin and
  // one switched off were linked alike.
  function heldLink(h) {
    const n = h.unacknowledged;
    const said = [
      ...(h.refused === 0 ? ["none heard"] : []), ...(n ? [`${n} alarm${plural(n)} waiting`] : []),
    ];
    const text = said.length ? `${h.device}: ${said.join(", ")}` : h.device;
    return el("a", { href: "/arm/" + encodeURIComponent(h.device), class: "held-arm", "data-device": h.device,
      title: h.why, text });
  }
  function heldLinks() {
    if (!held.length) return [];
    const links = held.flatMap((h, i) => [i ? " · " : "", heldLink(h)]);
    const line = el("p", {}, "Each held arm's page lists its servos' alarms, to acknowledge: ", ...links);
    if (held.length <= HELD_SHOWN) return [Object.assign(line, { id: "held-arms" })];
    const waiting = held.reduce((sum, h) => sum + h.unacknowledged, 0);
    const summary = `The ${held.length} held arms' pages (${waiting} alarm${plural(waiting)} waiting)`;
    const box = el("details", { id: "held-arms" }, el("summary", { text: summary }), line);
    box.open = Boolean(document.querySelector("details#held-arms[open]"));
    return [box];
  }

  let updates = 0, updateTotalMs = 0;
  function update(doc) {
    const t0 = performance.now();
    columns = Object.fromEntries(doc.columns.map((name, i) => [name, i]));
    rows = doc.rows;
    loaded = true;
    listening = doc.listening || null;
    now = doc.time || Date.now() / 1000;
    const s = doc.counts.status, a = doc.counts.alarmed_devices;
    held = doc.held || [];
    // The alarm counts take the held arms' worst alarms: "0 arms" beside "critical: 1" read as a wrong count.
    const heldWord = `${held.length} held, no card`;
    const heldCount = held.length ? [" · ", el("span", { id: "held-count", text: heldWord })] : [];
    counts.replaceChildren(el("b", { text: String(doc.counts.devices) }), " arms", ...heldCount, " · ",
      el("span", { class: "status ONLINE", text: `${s.ONLINE} online` }), " · ",
      el("span", { class: "status STALE", text: `${s.STALE} stale` }), " · ",
      el("span", { class: "status OFFLINE", text: `${s.OFFLINE} offline` }), " · ",
      // Arms, by their worst alarm (an arm with two alarms counts once), so the header's numbers add up.
      "arms whose worst alarm is ",
      el("span", { class: "sev-critical", text: `critical: ${a.critical}` }), " · ",
      el("span", { class: "sev-warning", text: `warning: ${a.warning}` }));
    const said = [...(doc.notices || [])];
    // A stop closes the broker connection on purpose: said as the stop it is, not as an outage to look for.
    if (listening && listening.stopping) {
      said.unshift("The agent is stopping (a restart, an update or a shutdown): it no longer receives the " +
        "arms' messages, so their figures are their last; the page comes back live with the agent.");
    } else if (listening && !listening.connected && rows.length) {
      // With arms listed, a broker outage otherwise reads as every arm going OFFLINE at once.
      said.unshift("The agent is not connected to its broker: no arm's messages reach it, so every arm " +
        "goes STALE, then OFFLINE, whatever it does. GET /healthz says why; the Events page says when.");
    }
    notices.replaceChildren(...said.map((text) => el("p", { text })), ...heldLinks());
    notices.hidden = !notices.childElementCount;
    filter();
    render();
    // What `twin bench console` reads: rows shown, updates handled and the mean time each took.
    updates += 1;
    updateTotalMs += performance.now() - t0;
    window.twinRows = rows.length;
    window.twinUpdates = updates;
    window.twinUpdateMs = updateTotalMs / updates;
    if (!document.body.dataset.ready) {
      document.body.dataset.ready = "1";
      window.twinReadyAt = performance.now();
    }
  }

  // The filters live in the page's address (/?status=OFFLINE&alarm=waiting), so a reload, the way back from
  // an arm's page and a link sent to a colleague show the same arms; a value the lists do not offer is left out.
  const LISTS = [["status", status], ["alarm", alarm], ["sort", sort]];
  const asked = new URLSearchParams(location.search);
  search.value = asked.get("q") || "";
  for (const [key, select] of LISTS) Twin.choose(select, asked.get(key) || "");
  function keepChosen() {
    const chosen = new URLSearchParams();
    // The defaults (an empty search, each list's first choice) stay out: a plain "/" is the page as it opens.
    if (search.value.trim()) chosen.set("q", search.value.trim());
    for (const [key, select] of LISTS) if (select.selectedIndex > 0) chosen.set(key, select.value);
    const query = chosen.toString();
    history.replaceState(null, "", location.pathname + (query ? "?" + query : "") + location.hash);
  }
  for (const input of [search, status, alarm, sort]) input.addEventListener("input", () => { keepChosen(); filter(); render(); });
  let pending = false;
  viewport.addEventListener("scroll", () => {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => { pending = false; render(); });
  });
  window.addEventListener("resize", render);
  setMode(mode);
  Twin.getJSON("/api/fleet").then(update).catch(() => Twin.setLink(false, "agent unreachable"));
  Twin.stream("/api/stream/fleet", { fleet: update });
})();
