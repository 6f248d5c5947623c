// One arm: live charts (joint angles; servo temperature, load and current) over the last minutes, its
// alarms with Acknowledge, loss and rejections by reason, a link to the Rerun view, and for an OFFLINE arm a
// button that forgets it (an arm retired for good).
"use strict";

(() => {
  const { el, main, device } = Twin;
  const WINDOW_S = 300;
  const COLORS = ["#2457c5", "#c0262d", "#1a7f37", "#b7791f", "#7b3fb5", "#0f8a8a"];
  const CHARTS = [
    { key: "angle", title: "joint angles (°)", pick: (d, j) => d.joints_rad && d.joints_rad[j] !== undefined ? d.joints_rad[j] * 180 / Math.PI : null },
    { key: "temperature", title: "servo temperature (C)", pick: (d, j) => servo(d, j, "temperature_c") },
    { key: "load", title: "servo load (% of stall)", pick: (d, j) => servo(d, j, "load_percent") },
    { key: "current", title: "servo current (A)", pick: (d, j) => servo(d, j, "current_a") },
  ];
  function servo(d, joint, field) {
    const s = d.servos && d.servos[joint];
    return s && s[field] !== null && s[field] !== undefined ? s[field] : null;
  }

  let joints = [];
  const samples = [];  // [time, {chart key: [value per joint]}, true: the arm went silent before it]
  let lastTimestamp = null;
  // The arm was STALE or OFFLINE at some tick since the last sample: the next sample starts a new line, so
  // the charts do not draw a straight line across a silence as if readings had come.
  let silent = false;
  let breaks = Twin.breaks();  // the page's breaks with the agent (a restart) start a new line too

  const title = el("h1", { text: device });
  const summary = el("div", { class: "kv", id: "summary" });
  const rerun = Twin.rerun
    ? el("a", { href: Twin.rerun, target: "_blank", rel: "noopener", id: "rerun-link", text: "open the fleet in the Rerun viewer" },)
    // Not served is not "off": the agent may still save a .rrd (the demo's twin.rrd), which `twin web` serves.
    : el("span", { class: "muted", text: "Rerun view: not served by this agent (twin run --rerun-serve; a saved .rrd opens with twin web FILE; docs/web.md)" });
  const charts = CHARTS.map((c) => {
    const canvas = el("canvas", { class: "chart", "data-chart": c.key, "data-points": "0" });
    const legend = el("div", { class: "legend" });
    return { ...c, canvas, legend, panel: el("div", { class: "panel" }, el("h2", { text: c.title }), canvas, legend) };
  });
  const alarmsBody = el("tbody");
  // The outcome of the last Acknowledge, kept outside the table: the live stream redraws the table whenever
  // a reading changes an alarm's value, and would wipe a refusal written into its row.
  const ackResult = el("p", { id: "ack-result", role: "status", hidden: true });
  // Forget: offered when the agent says it would forget the arm (doc.forget); its outcome stays on the page.
  const forgetButton = el("button", { type: "button", id: "forget", hidden: true, text: "Forget this arm" });
  const forgetResult = el("p", { id: "forget-result", role: "status", hidden: true });
  // An OFFLINE arm the agent would not forget: its words why, and what to do instead.
  const forgetHeld = el("p", { id: "forget-held", class: "muted", hidden: true });
  let forgotten = false;
  let shownAlarms = [];
  // Every alarm of the arm waiting for a person, in one go: one by one, ten hot arms took twenty clicks. Always
  // there (disabled with none waiting), beside the table's title: appearing, it would move the rows.
  const ackAllButton = el("button", { type: "button", id: "ack-all", disabled: true, text: "Acknowledge all (0)" });
  let ackAllBusy = false;
  // Its Acknowledge all cut short by a reload: said at once (Twin.interruptedAck), as on the Fleet page.
  const cut = Twin.interruptedAck();
  if (cut) {
    ackResult.hidden = false;
    ackResult.className = "ack-refused";
    ackResult.textContent = Twin.interruptedText(cut, '"Acknowledge all"');
  }
  const lossBox = el("div", { class: "kv" });
  const rejectsBody = el("tbody");
  main.append(
    // Its events are a link away: the Events page's device box filled in (a walk went there and typed the id).
    el("div", { class: "toolbar" }, el("a", { href: "/", text: "← fleet" }),
      el("a", { href: "/events?device=" + encodeURIComponent(device), id: "arm-events", text: "its events" })),
    title,
    el("div", { class: "grid2" },
      el("div", { class: "panel" }, summary, el("p", {}, rerun,
        el("span", { class: "muted", text: ` (this arm is arms/${device})` })),
        forgetButton, forgetHeld, forgetResult),
      el("div", { class: "panel" }, el("h2", { text: "loss" }), lossBox, el("h2", { text: "rejected messages by reason" }),
        el("table", {}, el("thead", {}, el("tr", {}, el("th", { text: "reason" }), el("th", { text: "messages" }))), rejectsBody))),
    // What an acknowledgement was answered comes under the table: above it, its first appearance pushed every
    // row down, and the next button with it, from under the pointer.
    el("h2", { class: "with-action" }, "alarms", ackAllButton),
    el("table", { id: "alarms" }, el("thead", {}, el("tr", {}, ...["alarm", "severity", "state", "value now", `in this state since (${Twin.zone()})`, "message", ""].map((t) => el("th", { text: t })))), alarmsBody),
    ackResult,
    el("h2", { text: "live, last 5 minutes" }),
    el("div", { class: "grid2" }, ...charts.map((c) => c.panel)));

  // Where the arm's LeRobot calibration came from; flagged when it has none while its units need one, with
  // how to push one to the store this agent reads: the agent writes that sentence, since only it knows its store.
  function calibration(d, push, held) {
    // Held (its file refused, none to keep): no calibration decodes it, the nominal one included.
    if (held) {
      return el("span", { class: "uncalibrated", id: "calibration-held", "data-command": push.command,
        text: `none: this agent holds this arm, as its calibration in the store is refused (${held}): ` +
          heldWords(d.health.counters.received > 0) + `; push a valid one: ${push.command}` });
    }
    const problem = d.calibration_problem ? ` (newest file refused: ${d.calibration_problem})` : "";
    if (d.uncalibrated) {
      return el("span", { class: "uncalibrated", id: "uncalibrated", "data-command": push.command,
        text: `none: the nominal SO-101's zero and range, not this arm's; ${push.text}${problem}` });
    }
    // A file refused while the agent ran: the twin keeps the calibration it read from that path before, and
    // the path alone read as if the broken file were in force. Said so, with the push that ends it.
    if (d.calibration_problem) {
      return el("span", { class: "uncalibrated", id: "calibration-refused", "data-command": push.command,
        text: `${d.calibration || "the one it had"}, as read before: the file there now is refused ` +
          `(${d.calibration_problem}), so the twin keeps that one; push a valid one: ${push.command}` });
    }
    return el("span", { text: d.calibration || "not needed for these units" });
  }

  // What holding does to the arm: "its messages are refused" was said of an arm nothing was received from
  // (switched off, or a wrong id on its edge), which sent the operator looking for a refused message.
  function heldWords(heard) {
    return heard
      ? "its messages are refused and its twin does not move (its servos' alarms are still checked)"
      : "nothing has been received from it since the agent started (check that the arm is on and publishes " +
        "under this id); once it does, its messages are refused and its twin stays still";
  }

  // A held arm's messages are all refused, yet they show it is on: its page read "last seen never, 0.0 Hz"
  // while it published ten a second. Said apart from the valid ones, so none reads as mirrored.
  function lastSeen(h) {
    if (h.age_s !== null) return `${Twin.num(h.age_s, 1)} s ago`;
    if (h.refused_age_s == null) return "never";
    return `never a valid message; a refused one ${Twin.num(h.refused_age_s, 1)} s ago (not mirrored)`;
  }
  // Null while not known (a worker started again, read from its checkpoint, or less than a window counted):
  // read as 0 it said "0.0 Hz" beside "a refused one 2 s ago".
  // So is the valid rate read from a checkpoint, which said "0.0 Hz" beside "last seen 0.1 s ago".
  function rate(h) {
    const known = h.rate_hz !== null;
    const valid = known ? `${Twin.num(h.rate_hz, 1)} Hz mirrored` : "mirrored rate not known yet";
    if (h.refused_rate_hz === null) return `${valid}, refused rate not known yet`;
    if (h.refused_rate_hz) return `${valid}, ${Twin.num(h.refused_rate_hz, 1)} Hz refused`;
    return known ? `${Twin.num(h.rate_hz, 1)} Hz` : "not known yet (its worker was started again)";
  }

  // The loss is read from gaps in the edge timestamps, counted in periods of [health] expected_rate_hz (the
  // edge sends no sequence number): an edge at 5 Hz against 10 showed a steady 50 % "loss", and the page
  // named no setting. Gaps all alike (core.loss's steady_periods) are a slower edge or a loss in a fixed
  // pattern on the way in, which the page cannot tell apart, so it names both and what tells them apart.
  // The quota only where the broker limits each connection, and the Fleet page's notice, not quoted: it is
  // the pool's, and this arm's connection may be under its budget.
  function lossBasis(d, expected, limited) {
    const setting = "[health] expected_rate_hz" + (expected ? ` = ${hz(expected)}` : "");
    const basis = `gaps in its edge timestamps, in periods of ${setting} (the edge sends no sequence number)`;
    const k = d.loss.steady_periods;
    if (!k || !d.loss.period_s) return `${basis}; an edge publishing slower than that reads as loss`;
    const edge = hz(1 / (d.loss.period_s * k));
    const quota = limited ? " (as by a broker connection over its per-connection quota: the Fleet page " +
      "says so in a notice once the connections cannot take the load on)" : "";
    return `${basis}. Every recent gap is ${k} periods, a fixed pattern, from either of two causes: its ` +
      `edge publishes at ~${edge} Hz, or its messages are lost in a fixed pattern on the way in${quota}. ` +
      `To tell them apart, read the rate configured on the edge itself: only if it is ${edge} Hz set ` +
      `expected_rate_hz = ${edge} in the agent config (on the twin host the stack's armRateHz) ` +
      '(docs/agent.md, "Loss")';
  }
  function hz(value) { return String(Math.round(value * 10) / 10); }

  function kv(box, pairs) {
    box.replaceChildren(...pairs.flatMap(([k, v]) => [el("span", { class: "muted", text: k }), v instanceof Node ? v : el("span", { text: v })]));
  }

  function record(d, now) {
    if (d.health.status !== "ONLINE") silent = true;
    if (!d.joints_rad) return;
    if (d.timestamp_ms === lastTimestamp) return;  // nothing new since the last tick
    lastTimestamp = d.timestamp_ms;
    if (!joints.length) joints = Object.keys(d.joints_rad);
    const values = {};
    for (const c of CHARTS) values[c.key] = joints.map((j) => c.pick(d, j));
    const broke = Twin.breaks() !== breaks;
    breaks = Twin.breaks();
    samples.push([now, values, (silent || broke) && samples.length > 0]);
    silent = false;
    while (samples.length && samples[0][0] < now - WINDOW_S) samples.shift();
  }

  function draw(chart, now) {
    const canvas = chart.canvas, ratio = window.devicePixelRatio || 1;
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== Math.round(w * ratio)) { canvas.width = Math.round(w * ratio); canvas.height = Math.round(h * ratio); }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.clearRect(0, 0, w, h);
    let lo = Infinity, hi = -Infinity, points = 0, gaps = 0;
    for (const [, values, gap] of samples) {
      if (gap) gaps++;  // silences drawn as breaks in the lines
      let any = false;
      for (const v of values[chart.key]) if (v !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); any = true; }
      if (any) points++;  // readings drawn: samples with at least one value
    }
    // The window grows with what the page has seen, up to WINDOW_S, so a fresh page shows its lines.
    const span = samples.length ? Math.min(WINDOW_S, Math.max(10, now - samples[0][0])) : WINDOW_S;
    const left = 44, right = 8, top = 8, bottom = 18;
    ctx.strokeStyle = "#d9dde5"; ctx.fillStyle = "#667085"; ctx.font = "11px sans-serif";
    ctx.strokeRect(left, top, w - left - right, h - top - bottom);
    // The axis's left end, as far back as it draws: whole minutes said "-2 min" of a 92 s axis.
    const axis = span < 120 ? `-${Math.round(span)} s` : `-${Number((span / 60).toFixed(1))} min`;
    ctx.fillText(axis, left, h - 4);
    ctx.fillText("now", w - right - 22, h - 4);
    canvas.dataset.points = String(points);
    canvas.dataset.axis = axis;
    canvas.dataset.gaps = String(gaps);
    if (!points) { ctx.fillText("no readings yet", left + 8, top + 16); return; }
    if (hi - lo < 1e-6) { hi += 1; lo -= 1; }
    const pad = (hi - lo) * 0.08; hi += pad; lo -= pad;
    ctx.fillText(hi.toFixed(1), 2, top + 10);
    ctx.fillText(lo.toFixed(1), 2, h - bottom);
    const x = (t) => left + (w - left - right) * (1 - (now - t) / span);
    const y = (v) => top + (h - top - bottom) * (1 - (v - lo) / (hi - lo));
    joints.forEach((joint, k) => {
      ctx.strokeStyle = COLORS[k % COLORS.length]; ctx.lineWidth = 1.5; ctx.beginPath();
      let pen = false;
      for (const [t, values, gap] of samples) {
        const v = values[chart.key][k];
        if (gap) pen = false;
        if (v === null) { pen = false; continue; }
        if (pen) ctx.lineTo(x(t), y(v)); else { ctx.moveTo(x(t), y(v)); pen = true; }
      }
      ctx.stroke();
    });
    if (!chart.legend.childElementCount) {
      chart.legend.replaceChildren(...joints.map((j, k) => { const i = el("i"); i.style.background = COLORS[k % COLORS.length]; return el("span", {}, i, j); }));
    }
  }

  function notSaved(result) { return result.status === 503 && (result.payload || {}).error === "not_saved"; }

  // What the agent answered, in its own words (Twin.refusal).
  function ackOutcome(alarm, result) {
    if (result.ok) {
      const now = result.payload && result.payload.alarms && result.payload.alarms[0];
      // A LATCHED alarm acknowledged is reset to NORMAL: the Events page records it as "reset", so the
      // page says the same word a search there finds.
      const done = now && now.state === "NORMAL" ? "reset (acknowledged after it cleared)" : "acknowledged";
      return `${alarm.alarm_id} ${done}${now ? `: now ${now.state}` : ""}`;
    }
    // Made, but the state file could not keep it: "not acknowledged" would be wrong, "acknowledged" too little.
    if (notSaved(result)) return `${alarm.alarm_id} acknowledged, but not kept: ${Twin.refusal(result)}`;
    if (doneElsewhere(result)) {
      // NORMAL: it cleared since the row was drawn (reset by another click, or a warning that does not
      // latch), which "acknowledged already" would misstate; the agent's 409 says which state it found.
      // Its detail says the same again, so the page's sentence stands alone.
      const why = result.payload.state === "NORMAL" ? "was already cleared (nothing waits for a person)"
        : "was acknowledged already (another tab, person or script did it first)";
      return `${alarm.alarm_id} ${why}`;
    }
    return `${alarm.alarm_id} was not acknowledged: ${Twin.refusal(result)}`;
  }

  // 409 nothing_to_acknowledge: the alarm is ACKNOWLEDGED, or NORMAL (cleared), since the row was drawn.
  // Nothing is left for the click to do: a walk's second tab read a red "was not acknowledged", where
  // Acknowledge all counts the same answers as "already acknowledged" and "already cleared".
  function doneElsewhere(result) {
    return result.status === 409 && !!result.payload && result.payload.error === "nothing_to_acknowledge";
  }

  async function acknowledge(alarm, button) {
    button.disabled = true;
    const id = alarm.alarm_id.split("/").map(encodeURIComponent).join("/");
    let result;
    try {
      result = await Twin.post(`/alarms/${id}/ack`);
    } catch (_) {
      result = { ok: false, status: 0, payload: null };  // no answer at all: the agent is down or restarting
    }
    button.disabled = false;
    ackResult.hidden = false;
    const done = result.ok || doneElsewhere(result);
    ackResult.className = done ? "ack-ok" : "ack-refused";
    ackResult.textContent = ackOutcome(alarm, result);
    if (done) {
      // The stream shows the new state within a tick anyway; this only shows it sooner.
      Twin.getJSON("/alarms?device=" + encodeURIComponent(device))
        .then((doc) => renderAlarms(doc.alarms), () => {});
    }
  }

  function waitingAlarms() { return shownAlarms.filter((a) => Twin.WAITING.has(a.state)); }

  function showAckAll() {
    const n = waitingAlarms().length;
    setText(ackAllButton, `Acknowledge all (${n})`);
    ackAllButton.disabled = ackAllBusy || n === 0;
  }

  // The confirmation names how many and which; only those are sent (Twin.acknowledgeMany).
  async function acknowledgeAll() {
    const targets = waitingAlarms();
    if (!targets.length) return;
    const names = targets.map((a) => `${a.joint} ${a.kind} (${a.state})`).join(", ");
    if (!window.confirm(`Acknowledge ${targets.length} alarm${targets.length === 1 ? "" : "s"} of ${device}? ${names}`)) return;
    ackAllBusy = true;
    showAckAll();
    const tally = await Twin.acknowledgeMany(targets);
    ackAllBusy = false;
    showAckAll();
    ackResult.hidden = false;
    ackResult.className = Twin.tallyOk(tally) ? "ack-ok" : "ack-refused";
    ackResult.textContent = `${device}: ${Twin.tallyText(tally)}`;
    Twin.getJSON("/alarms?device=" + encodeURIComponent(device)).then((doc) => renderAlarms(doc.alarms), () => {});
  }
  ackAllButton.addEventListener("click", acknowledgeAll);

  // What forgetting removes, said before the operator confirms: the alarms are the ones this page shows.
  function forgetQuestion() {
    const byState = {};
    for (const a of shownAlarms) byState[a.state] = (byState[a.state] || 0) + 1;
    const alarmsText = Object.keys(byState).length
      ? ` and ${Object.entries(byState).map(([state, n]) => `${n} ${state}`).join(", ")} alarm(s) (also from ` +
        "the state file)"
      : " (it has no alarm)";
    return `Forget ${device}? The agent removes its twin, its health and message counters and its loss ` +
      `estimate${alarmsText}; it leaves the Fleet page. If it publishes again it comes back as a new arm.`;
  }

  function forgetOutcome(result) {
    if (result.ok) {
      const removed = Object.entries((result.payload && result.payload.alarms_removed) || {});
      const alarmsText = removed.length ? removed.map(([state, n]) => `${n} ${state}`).join(", ") : "none";
      return `${device} is forgotten: its twin, health and counters are removed; alarms removed: ${alarmsText}. `;
    }
    if (notSaved(result)) return `${device} is forgotten, but not kept: ${Twin.refusal(result)}`;
    // No answer in time: the request still waits for the arm's mirror, so "was not forgotten" may be untrue.
    // The agent's detail says so and what to do, whichever of its waits ran out.
    if (result.payload && result.payload.error === "forget_timed_out") {
      return `Not known whether ${device} is forgotten: ${Twin.refusal(result)}`;
    }
    return `${device} was not forgotten: ${Twin.refusal(result)}`;
  }

  async function forget() {
    if (!window.confirm(forgetQuestion())) return;
    forgetButton.disabled = true;
    let result;
    try {
      result = await Twin.post(`/api/arm/${encodeURIComponent(device)}/forget`);
    } catch (_) {
      result = { ok: false, status: 0, payload: null };
    }
    forgetButton.disabled = false;
    forgetResult.hidden = false;
    forgetResult.className = result.ok ? "ack-ok" : "ack-refused";
    forgetResult.textContent = forgetOutcome(result);
    if (result.ok) {
      forgotten = true;
      forgetResult.append(el("a", { href: "/", id: "forget-fleet", text: "back to the Fleet page" }));
      showForgotten();
    }
  }
  forgetButton.addEventListener("click", forget);

  // After a forget the agent no longer knows the arm: the page says so instead of "not known". The title
  // and the forget's own answer say it is forgotten; a third "was forgotten" here read as a repeat.
  function showForgotten() {
    title.textContent = `${device}: forgotten`;
    summary.replaceChildren(el("p", { id: "forgotten", text: "If it publishes again it comes back as a new " +
      "arm, and this page fills in by itself." }));
    clearArm();
  }

  // An arm the agent no longer knows (forgotten here, or by another page or a script while this one was
  // open) has nothing left to act on or to read: a walk found its alarms still offered to Acknowledge (the
  // agent answers 404), "Forget this arm" still shown, and its loss figures as if live.
  function clearArm() {
    forgetButton.hidden = forgetHeld.hidden = true;
    shownAlarms = [];
    renderAlarms([]);
    lossBox.replaceChildren();
    rejectsBody.replaceChildren();
  }

  function servoErrors(d, motorIds) {
    const servos = d.servos;
    // No readings: an arm read from its worker's last checkpoint (the agent stopping, the worker restarting)
    // has none kept, and "not sent by the edge" was wrong of an edge that sends them.
    if (!servos) return d.mirror && d.mirror !== "running" ? `not known while its worker is ${d.mirror}` : "none received yet";
    const said = Object.entries(servos || {}).filter(([, s]) => s.errors && s.errors.length)
      .map(([joint, s]) => `${joint} servo (motor id ${motorIds[joint] ?? "?"}): ${s.errors.join(", ")}`);
    if (said.length) return said.join("; ");
    return Object.values(servos).some((s) => s.errors) ? "none" : "not sent by the edge";
  }

  // Why received and applied differ (a walk read "4007 received, 3990 applied" with no reason): the counters
  // /state gives, each named only when it is not zero.
  function notApplied(c) {
    const parts = [[c.coalesced, "coalesced (a newer one was waiting)"], [c.ignored_stale, "older than the last"],
      [c.rejected_total, "rejected"], [c.overwritten, "dropped behind"], [c.errors, "errors"]]
      .filter(([n]) => n).map(([n, what]) => `${n} ${what}`);
    return parts.length ? parts.join(", ") : "none";
  }

  // One row per alarm, kept across updates and changed in place. A reading changes an alarm's value at each
  // tick while the servo heats or cools; a row rebuilt then replaced the button under the operator's
  // pointer, and a click pressed on the old button and released on the new one was lost without a word.
  const alarmRows = new Map();  // alarm_id -> { tr, cells, button, alarm }
  const noAlarm = el("tr", {}, el("td", { colspan: 7, class: "muted", text: "no alarm" }));

  function setText(node, text) {
    if (node.textContent !== text) node.textContent = text;
  }

  function alarmRow(a) {
    const button = el("button", { type: "button", class: "primary", "data-alarm": a.alarm_id, text: "Acknowledge" });
    // The labels head each cell where the table stacks (console.css): its header row is hidden there.
    const cells = { name: el("td", { class: "wrap" }), severity: el("td", { "data-label": "severity" }),
      state: el("td", { class: "alarm-state", "data-label": "state" }),
      value: el("td", { class: "wrap", "data-label": "value now" }),
      since: el("td", { class: "wrap", "data-label": `in this state since (${Twin.zone()})` }),
      message: el("td", { class: "msg" }) };
    // What to do at the arm, under the message: the page may be all the operator has open.
    const text = el("span"), advice = el("div", { class: "advice" });
    cells.message.append(text, advice);
    const row = { tr: el("tr", { "data-alarm": a.alarm_id }, ...Object.values(cells), el("td", {}, button)),
      cells, button, alarm: a, text, advice };
    button.addEventListener("click", () => acknowledge(row.alarm, button));
    return row;
  }

  function fillAlarmRow(row, a) {
    const c = row.cells;
    row.alarm = a;
    row.tr.dataset.state = a.state;
    // A break allowed after each "_": a narrow column broke "over_temperature_critical" as "over_temperatu /
    // re_critical". Built once per row: its name does not change.
    const name = `${a.joint} ${a.kind}`;
    if (c.name.dataset.name !== name) {
      c.name.dataset.name = name;
      const parts = name.split("_");
      c.name.replaceChildren(...parts.flatMap((part, i) => (i < parts.length - 1 ? [part + "_", el("wbr")] : [part])));
    }
    setText(c.severity, a.severity);
    c.severity.className = "sev-" + a.severity;
    setText(c.state, a.state);
    // A servo error's value is the status's error bits, named in its message: a limit says nothing there.
    setText(c.value, a.kind === "servo_error"
      ? (a.value == null ? "–" : `status bits ${a.value}`)
      : `${Twin.num(a.value, 1)} ${a.unit} (limit ${a.threshold})`);
    setText(c.since, Twin.time(a.changed_at));
    // The message was written as the alarm rose and keeps that reading; the value beside it is today's (a
    // walk read "80.0 C" next to "at 75 C" and took one for wrong).
    setText(row.text, a.message ? `When raised: ${a.message}` : "");
    setText(row.advice, a.advice ? `What to do: ${a.advice}` : "");
    row.button.hidden = !Twin.WAITING.has(a.state);
  }

  function renderAlarms(alarms) {
    shownAlarms = alarms;
    showAckAll();
    const ids = new Set(alarms.map((a) => a.alarm_id));
    for (const id of [...alarmRows.keys()]) if (!ids.has(id)) alarmRows.delete(id);
    if (!alarms.length) {
      if (alarmsBody.firstChild !== noAlarm) alarmsBody.replaceChildren(noAlarm);
      return;
    }
    const order = alarms.map((a) => {
      let row = alarmRows.get(a.alarm_id);
      if (!row) { row = alarmRow(a); alarmRows.set(a.alarm_id, row); }
      fillAlarmRow(row, a);
      return row.tr;
    });
    // Rows move only when the set or the order of alarms changes.
    const shown = [...alarmsBody.children];
    if (order.length !== shown.length || order.some((tr, i) => tr !== shown[i])) alarmsBody.replaceChildren(...order);
  }

  // Held by its calibration (refused at the start): its messages come and are refused, so "no valid message"
  // is true, but the id is right and the fix is a push, not a check of the id. Its servos' alarms are still
  // raised from the refused messages, and no Fleet card shows them: this page lists them to acknowledge (a
  // walk found the table saying "no alarm" beside three critical ones).
  function held(doc) {
    title.textContent = `${device}: held, its calibration is refused`;
    // Its refused messages are all that shows it is on: how many, and when the last came (not mirrored).
    const r = doc.refused;
    const heard = r ? `${r.count} of its messages were refused so far (the last ${Twin.num(r.age_s, 1)} s ` +
      "ago), none mirrored; its twin does not move and its servos' alarms are still checked, listed below"
      : heldWords(false);
    summary.replaceChildren(el("p", { id: "unknown", text: `This agent holds this arm: its calibration in the ` +
      `store is refused (${doc.calibration_refused}), so ${heard}. Push a valid one: ` +
      `${doc.calibration_push.command}. This page fills in by itself once it is read.` }));
    // Not clearArm: its rows must stay the same elements from one frame to the next, under the pointer.
    forgetButton.hidden = forgetHeld.hidden = true;
    lossBox.replaceChildren();
    rejectsBody.replaceChildren();
    renderAlarms(doc.alarms || []);
  }

  // An id this agent has had no valid message from (mistyped, or an arm not heard yet): the page says what
  // to check instead of empty panels under a bare "not known", and fills in by itself once the arm is heard.
  function unknown(doc) {
    if (doc && doc.calibration_refused) { held(doc); return; }
    title.textContent = `${device}: not known to this agent`;
    // An arm this page has shown and the agent dropped was not "never heard": it was forgotten elsewhere, or
    // the agent started again and has not heard it yet; the sentence says so rather than blame the id.
    if (!shown) askForgotten();
    const text = shown
      ? "This agent no longer knows this arm: it was forgotten (the Events page has a twin event for it), " +
        "or the agent started again and has not heard the arm since. This page fills in by itself once it " +
        "is heard."
      : forgottenAt
        ? `This arm was forgotten at ${Twin.time(forgottenAt)} (${Twin.zone()}; the Events page has its twin ` +
          "event), and this agent has not heard it since. If it publishes again it comes back as a new arm, " +
          "and this page fills in by itself."
        : "This agent has had no valid message from an arm with this id since it started. Check the id " +
          "against the Fleet page, which lists every arm it has heard; this page fills in by itself once the " +
          "arm is heard.";
    summary.replaceChildren(el("p", { id: "unknown", text }));
    clearArm();
  }

  // A page opened (or reloaded) on an arm this agent forgot said it had "no valid message from an arm with
  // this id since it started", untrue of an arm heard and forgotten, and told the operator to check the id.
  // The arm's newest twin event says whether it was forgotten, and when: asked once, not at every frame (again
  // only after an ask that got no answer at all; one the agent refused is not asked again).
  let forgottenAt;  // undefined: not asked (or no answer); null: not forgotten, or refused; else epoch seconds
  function askForgotten() {
    if (forgottenAt !== undefined) return;
    forgottenAt = null;
    Twin.getJSON(`/api/events?device=${encodeURIComponent(device)}&kind=twin&limit=1`).then((doc) => {
      const last = doc.events[doc.events.length - 1];
      if (!last || !last.data || last.data.action !== "forgotten") return;
      forgottenAt = last.time;
      if (!shown && !forgotten) unknown(null);
    }, (error) => { forgottenAt = error && error.status ? null : undefined; });
  }

  // The agent's own answer (doc.forget), not a rule of the page's: the page's, on its clock and not the
  // worker's, offered forgets the agent refused, and named the wrong fix for an arm with too many devices.
  // Why not is said for an OFFLINE arm only: any other's status says it.
  function offerForget(h, doc) {
    const offer = doc.forget || { allowed: false, why: "" };
    forgetButton.hidden = !offer.allowed;
    forgetHeld.hidden = offer.allowed || h.status !== "OFFLINE" || !offer.why;
    forgetHeld.textContent = `Not offered: ${offer.why}.`;
  }

  let shown = false;  // this page has shown the arm's state at least once
  function update(doc) {
    const d = doc.device;
    if (!d) { if (forgotten) showForgotten(); else unknown(doc); return; }
    shown = true;
    title.textContent = device;
    shownAlarms = doc.alarms;
    offerForget(d.health, doc);
    const now = doc.time, h = d.health;
    kv(summary, [
      ["status", el("span", { class: "status " + h.status, text: h.status })],
      ["last seen", lastSeen(h)],
      ["rate", rate(h)],
      ["units", d.units], ["mode", d.mode],
      ["calibration", calibration(d, doc.calibration_push, doc.calibration_refused)],
      // The counters begin at the agent's start: said, so a restart's zeros do not read as a silent arm.
      ["messages", `${h.counters.received} received, ${h.counters.applied} applied` +
        (doc.agent_started_at ? ` since the agent started (${Twin.time(doc.agent_started_at)}, ${Twin.zone()})` : "")],
      // A row of its own, always there: a reason appearing mid-view must not move the alarms under the pointer.
      ["not applied", notApplied(h.counters)],
      // What the servos themselves report wrong (their status registers), by servo; always there, as above.
      ["servo errors", servoErrors(d, doc.motor_ids || {})],
    ]);
    kv(lossBox, [
      ["lost (estimated)", `${d.loss.lost} of ${d.loss.received + d.loss.lost} (${Twin.num(d.loss.loss_ratio * 100, 2)} %)`],
      ["recent window", `${d.loss.recent_lost} (${Twin.num(d.loss.recent_loss_ratio * 100, 2)} %)${d.loss.losing ? " — losing now" : ""}`],
      // Always there, as the rows above: a row appearing mid-view must not move the alarms under the pointer.
      ["estimated from", el("span", { id: "loss-basis",
        text: lossBasis(d, doc.expected_rate_hz, doc.per_connection_limit) })],
    ]);
    const reasons = Object.entries(h.counters.rejected || {});
    rejectsBody.replaceChildren(...(reasons.length ? reasons.map(([r, n]) => el("tr", {}, el("td", { text: r }), el("td", { text: String(n) })))
      : [el("tr", {}, el("td", { colspan: 2, class: "muted", text: "none" }))]));
    renderAlarms(doc.alarms);
    record(d, now);
    for (const c of charts) draw(c, now);
    if (!document.body.dataset.ready) { document.body.dataset.ready = "1"; window.twinReadyAt = performance.now(); }
  }

  Twin.getJSON("/api/arm/" + encodeURIComponent(device)).then(update).catch(unknown);
  Twin.stream("/api/stream/arm/" + encodeURIComponent(device), { arm: update });
})();
