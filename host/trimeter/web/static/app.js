"use strict";
// The trimeter page: a client of the JSON API (/api/openapi.json) and its event websocket. Plain JS + SVG:
// no build step and nothing fetched from outside (the LAN may have no internet).

const STATE_WORDS = {ready: "Ready", working: "Working", asking_empty_holder: "Empty the holder",
  next_sample: "Insert the next sample", failed: "Last job failed", connecting: "Connecting…", stopped: "Stopped"};
const COLORS = ["#1d2330", "#2364d2", "#d2691e", "#1f8a4c"];
let status = null;
let socket = null;

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v;
    else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
    else if (v !== null && v !== undefined && v !== false) node.setAttribute(k, v);
  }
  for (const c of children.flat()) node.append(c instanceof Node ? c : document.createTextNode(String(c ?? "")));
  return node;
}
const $ = (id) => document.getElementById(id);

async function api(path, options = {}) {
  const init = {credentials: "same-origin", ...options};
  if (options.json !== undefined) {
    init.method = init.method || "POST";
    init.headers = {"Content-Type": "application/json"};
    init.body = JSON.stringify(options.json);
  }
  const response = await fetch(path, init);
  const body = await response.json().catch(() => ({}));
  if (!response.ok) throw new Error(body.error ? body.error.message : `HTTP ${response.status}`);
  return body;
}

function fmtAge(s) {
  if (s === null || s === undefined) return "";
  if (s < 90) return `${Math.round(s)} s`;
  if (s < 5400) return `${Math.round(s / 60)} min`;
  return `${(s / 3600).toFixed(1)} h`;
}

// ----------------------------------------------------------------------------- live status
function connectEvents() {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  socket = new WebSocket(`${proto}://${location.host}/api/events`);
  socket.onopen = () => { $("conn").textContent = "live"; $("conn").className = "pill live"; };
  socket.onclose = () => {
    $("conn").textContent = "offline"; $("conn").className = "pill down";
    setTimeout(connectEvents, 2000);
  };
  socket.onmessage = (msg) => {
    const record = JSON.parse(msg.data);
    if (record.type === "status") { status = record.status; renderStatus(); return; }
    if (record.type === "progress") { showProgress(record.step, record.progress); return; }
    if (record.type === "event") addLog(record);
    refreshStatus();
  };
}

let statusTimer = null;
function refreshStatus() {
  if (statusTimer) return;
  statusTimer = setTimeout(async () => {
    statusTimer = null;
    try { status = await api("/api/status"); renderStatus(); } catch (e) { /* the socket shows offline */ }
  }, 150);
}

function showProgress(step, fraction) {
  if (!$("step")) return;
  $("step").textContent = step || "idle";
  $("bar-fill").style.width = `${Math.round(100 * (fraction || 0))}%`;
}

function addLog(record) {
  const log = $("log");
  if (!log) return;
  const time = record.time_utc.slice(11, 19);
  log.prepend(el("li", {class: record.kind}, el("span", {class: "kind"}, `${time} ${record.kind}`), record.message));
  while (log.children.length > 60) log.lastChild.remove();
}

function renderStatus() {
  if (!status || !$("state")) return;
  const state = $("state");
  state.textContent = STATE_WORDS[status.state] || status.state;
  state.className = `state ${status.state}`;
  const cal = status.calibration;
  $("calibration").textContent = !cal ? "none yet" : cal.due ? `due: ${cal.due}` :
    `${fmtAge(cal.age_s)} old (max ${fmtAge(cal.max_age_s)})`;
  const drift = status.lamp_drift;
  $("drift").textContent = drift && drift.drift !== null ? `${(100 * drift.drift).toFixed(3)} % at warm-up` : "—";
  const dev = status.device;
  $("device").textContent = dev ? `${dev.port} · fw ${dev.firmware}` : "not connected";
  const table = status.map_table;
  $("maptable").textContent = !table ? "—" : table.error ? table.error : !table.slot ? "none active" :
    `slot ${table.slot} ${table.matches_fit_table ? "✓ matches" : "≠ not this host's"}`;
  showProgress(status.step, status.progress);
  renderAsk();
  const busy = status.job !== null;
  $("measure-btn").disabled = busy || status.state === "asking_empty_holder";
  $("calibrate-btn").disabled = busy;
  const form = $("measure-form");
  if (form && !form.dataset.filled && status.samples.length) {
    form.thickness_mm.value = status.samples[0].thickness_mm;
    if (status.samples[1]) form.second_thickness_mm.value = status.samples[1].thickness_mm;
    form.dataset.filled = "1";
  }
  renderRecent();
}

function renderAsk() {
  const box = $("ask");
  box.replaceChildren();
  const ask = status.asking;
  if (!ask) { box.classList.add("hidden"); return; }
  box.classList.remove("hidden");
  if (ask.what === "empty_holder") {
    box.append(el("p", {}, el("b", {}, "Calibration: "), `${ask.reason || "a calibration is due"}. `,
      "Take the sample out of the holder, then confirm (or press the instrument's button)."),
    el("button", {id: "holder-empty", onclick: () => act(() => api("/api/calibrate", {json: {holder_empty: true}}),
      "calibrating: holder check, warm-up, calibration")}, "Holder is empty"));
  } else {
    box.append(el("p", {}, el("b", {}, "Next sample: "), "put the next sample in, then confirm (or press the button)."),
      el("button", {id: "next-sample", onclick: () => act(() => api("/api/next-sample", {json: {}}), "measuring")},
        "Next sample is in"));
  }
}

function renderRecent() {
  const box = $("recent");
  if (!box) return;
  const rows = status.recent_jobs.slice(0, 6).map((j) => el("tr", {},
    el("td", {}, j.finished_utc ? j.finished_utc.slice(11, 19) : ""), el("td", {}, `${j.kind} (${j.source})`),
    el("td", {class: j.state === "failed" ? "flag" : "clean"}, j.outcome || j.state),
    el("td", {}, j.measurement ? el("a", {href: `#/m/${j.measurement}`}, j.measurement) : j.message)));
  box.replaceChildren(rows.length ? el("table", {}, el("tbody", {}, rows)) : el("p", {class: "msg"}, "no jobs yet"));
}

async function act(request, note) {
  const msg = $("action-msg");
  try {
    const answer = await request();
    if (msg) { msg.className = "msg"; msg.textContent = note; }
    return answer;
  } catch (e) {
    if (msg) { msg.className = "msg error"; msg.textContent = e.message; }
  }
}

// ---------------------------------------------------------------------------------- views
function mount(id) {
  const view = $("view");
  view.replaceChildren($(id).content.cloneNode(true));
}

async function homeView() {
  mount("tpl-home");
  $("measure-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const f = ev.target;
    const body = {thickness_mm: Number(f.thickness_mm.value)};
    if (f.label.value) body.label = f.label.value;
    if (f.second_thickness_mm.value) body.second_thickness_mm = Number(f.second_thickness_mm.value);
    const answer = await act(() => api("/api/measure", {json: body}), "measuring…");
    if (answer) followJob(answer.job.id);
  });
  $("calibrate-btn").addEventListener("click", () =>
    act(() => api("/api/calibrate", {json: {}}), "empty the holder, then confirm above"));
  status = await api("/api/status");
  renderStatus();
  renderInstruments();
}

// ------------------------------------------------------------- several instruments (serve with [[instruments]])
let instrumentsTimer = null;
async function renderInstruments() {
  clearTimeout(instrumentsTimer);
  const body = $("instruments");
  if (!body) return;  // another view is shown
  let listing;
  try { listing = await api("/api/instruments"); } catch (e) { return; }  // one instrument: no panel
  $("instruments-card").classList.remove("hidden");
  body.replaceChildren(...listing.instruments.map(instrumentRow));
  instrumentsTimer = setTimeout(renderInstruments, 2000);
}

function instrumentRow(i) {
  const base = `/instruments/${encodeURIComponent(i.name)}/api`;
  const cal = i.calibration;
  const table = i.map_table;
  const say = (text, error = false) => {
    $("instruments-msg").className = error ? "msg error" : "msg";
    $("instruments-msg").textContent = `${i.name}: ${text}`;
  };
  const post = async (path, json, note) => {
    try { await api(`${base}/${path}`, {json}); say(note); } catch (e) { say(e.message, true); }
    renderInstruments();
  };
  const measure = () => {
    const form = $("measure-form");
    const thickness = form && form.thickness_mm.value ? Number(form.thickness_mm.value) : i.samples[0].thickness_mm;
    post("measure", {thickness_mm: thickness}, "measuring…");
  };
  const asking = i.state === "asking_empty_holder";
  const busy = i.job !== null;
  const jobs = i.recent_jobs.slice(0, 3).map((j) => el("div", {class: j.state === "failed" ? "flag" : ""},
    `${j.kind} ${j.outcome || j.state} `, j.measurement ? el("a", {href: `#/m/${j.measurement}`}, j.measurement) : ""));
  if (i.job) jobs.unshift(el("div", {}, `${i.job.kind} ${i.job.state}…`));
  return el("tr", {"data-instrument": i.name},
    el("td", {}, el("b", {}, i.name)), el("td", {}, `${i.port} @${i.address}`),
    el("td", {class: `state ${i.state}`}, STATE_WORDS[i.state] || i.state),
    el("td", {}, !cal ? "none yet" : cal.due ? `due: ${cal.due}` : `${fmtAge(cal.age_s)} old`),
    el("td", {}, !table ? "—" : table.error ? table.error : !table.slot ? "none active" : `slot ${table.slot}`),
    el("td", {}, jobs.length ? jobs : "—"),
    el("td", {},
      asking ? el("button", {onclick: () => post("calibrate", {holder_empty: true}, "calibrating…")}, "Holder is empty")
        : el("button", {class: "secondary", disabled: busy, onclick: () => post("calibrate", {},
          "empty its holder, then confirm")}, "Calibrate…"),
      el("button", {disabled: busy || asking, onclick: measure}, "Measure")));
}

async function followJob(id) {
  // the result page opens by itself once the measurement is written
  for (;;) {
    await new Promise((r) => setTimeout(r, 500));
    let job;
    try { job = (await api(`/api/jobs/${id}`)).job; } catch (e) { return; }
    if (job.state === "done" || job.state === "failed") {
      if (job.measurement) {
        location.hash = `#/m/${job.measurement}`;
      } else if (job.state === "failed") {
        const msg = $("action-msg");
        if (msg) { msg.className = "msg error"; msg.textContent = `${job.outcome}: ${job.message}`; }
      }
      return;
    }
  }
}

let historyOffset = 0;
const PAGE = 25;
async function historyView() {
  mount("tpl-history");
  const form = $("search");
  const query = () => {
    const q = new URLSearchParams();
    for (const k of ["label", "instrument", "since", "until", "flagged"]) if (form[k].value) q.set(k, form[k].value);
    return q;
  };
  const selected = new Set();
  const load = async () => {
    const q = query();
    const csv = new URLSearchParams(q); csv.set("format", "csv");
    $("csv").href = `/api/measurements?${csv}`;
    q.set("limit", PAGE); q.set("offset", historyOffset);
    const page = await api(`/api/measurements?${q}`);
    $("rows").replaceChildren(...page.measurements.map((m) => el("tr", {},
      el("td", {}, el("input", {type: "checkbox", onchange: (e) => {
        e.target.checked ? selected.add(m.id) : selected.delete(m.id);
        $("compare").disabled = selected.size !== 2;
      }})),
      el("td", {}, m.written_utc.replace("T", " ").slice(0, 19)),
      el("td", {}, m.label || "—", m.refit_of ? el("span", {class: "msg"}, " (re-fit)") : ""),
      el("td", {}, m.instrument || "—"),
      el("td", {}, m.thicknesses_mm.map((t) => `${t} mm`).join(" + ")),
      el("td", {}, m.maps.join(", ")), el("td", {}, m.method || ""),
      el("td", {}, m.flagged_bins ? el("span", {class: "flag", title: m.flag_names.join(", ")},
        `${m.flagged_bins} / ${m.bins}`) : el("span", {class: "clean"}, "none")),
      el("td", {}, el("a", {href: `#/m/${m.id}`}, "open ›")))));
    const last = Math.min(page.total, historyOffset + PAGE);
    $("page").textContent = page.total ? `${historyOffset + 1}–${last} of ${page.total}` : "no measurements";
    $("prev").disabled = historyOffset === 0;
    $("next").disabled = last >= page.total;
  };
  form.addEventListener("submit", (e) => { e.preventDefault(); historyOffset = 0; load(); });
  $("prev").onclick = () => { historyOffset = Math.max(0, historyOffset - PAGE); load(); };
  $("next").onclick = () => { historyOffset += PAGE; load(); };
  $("compare").onclick = () => { location.hash = `#/compare/${[...selected].join("/")}`; };
  await load();
}

async function measurementView(id) {
  mount("tpl-measurement");
  const d = await api(`/api/measurements/${encodeURIComponent(id)}`);
  const m = d.measurement;
  $("m-title").textContent = `${m.label || "Measurement"} · ${m.written_utc.replace("T", " ").slice(0, 19)} UTC`;
  const fact = (k, v) => el("div", {}, el("b", {}, k), v);
  $("m-facts").replaceChildren(fact("Thickness", m.thicknesses_mm.map((t) => `${t} mm`).join(" + ")),
    fact("Map", m.maps.join(", ")), fact("Method", m.method || ""),
    fact("Flagged bins", `${m.flagged_bins} of ${m.bins}`),
    ...(m.refit_of ? [fact("Re-fit of", el("a", {href: `#/m/${m.refit_of}`}, m.refit_of))] : []),
    ...(m.incomplete ? [fact("Incomplete", m.incomplete)] : []));
  const p = d.parameters;
  $("m-plot").replaceChildren(plotParameters([{params: p.combined, color: COLORS[0], band: true, name: "combined"},
    ...p.per_thickness.map((q, i) => ({params: q, color: COLORS[i + 1], dashed: true, name: `ℓ = ${q.thickness_mm} mm`}))],
  {beer: p.combined}));
  const flags = $("m-flags");
  flags.replaceChildren(
    ...(d.advice.length ? d.advice.map((a) => el("div", {class: "advice"}, a))
      : [el("p", {class: "clean"}, "Every bin fitted cleanly: nothing to do.")]),
    ...(Object.keys(d.flag_counts).length ? [el("p", {class: "msg"}, "Flags per bin: ",
      Object.entries(d.flag_counts).map(([k, v]) => `${k} ×${v}`).join(", "))] : []));
  const base = `/api/measurements/${encodeURIComponent(id)}`;
  $("m-files").replaceChildren(el("a", {href: `${base}/zip`}, "⬇ all (zip)"),
    ...d.files.map((f) => el("a", {href: `${base}/files/${encodeURIComponent(f)}`, target: "_blank"}, f)));
  const maps = await api("/api/maps");
  const form = $("refit");
  form.map.replaceChildren(...maps.maps.map((n) => el("option", {value: n, selected: m.maps[0] === n}, n)));
  form.method.replaceChildren(...maps.methods.map((n) => el("option", {value: n, selected: m.method === n}, n)));
  form.map.disabled = m.thicknesses_mm.length !== 1;   // two thicknesses: their own maps
  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    const body = {method: form.method.value};
    if (!form.map.disabled) body.maps = [form.map.value];
    const msg = $("refit-msg");
    try {
      const job = (await api(`${base}/refit`, {json: body})).job;
      msg.className = "msg"; msg.textContent = "re-fitting…";
      followJob(job.id);
    } catch (err) { msg.className = "msg error"; msg.textContent = err.message; }
  });
}

// a series' colour key: set through the CSSOM, which the page's CSP allows (a style attribute it refuses)
function swatch(color) {
  const node = el("i");
  node.style.background = color;
  return node;
}

async function compareView(a, b) {
  mount("tpl-compare");
  const [da, db] = await Promise.all([a, b].map((id) => api(`/api/measurements/${encodeURIComponent(id)}`)));
  const series = [da, db].map((d, i) => ({params: d.parameters.combined, color: COLORS[i + 1], band: true,
    name: `${d.measurement.label || d.measurement.id} · ${d.measurement.maps.join(" + ")} · ${d.measurement.method} · ` +
      `${d.measurement.written_utc.replace("T", " ").slice(0, 19)}${d.measurement.refit_of ? " (re-fit)" : ""}`}));
  $("c-legend").replaceChildren(...series.map((s) => el("span", {}, swatch(s.color),
    el("a", {href: `#/m/${[a, b][series.indexOf(s)]}`}, s.name))));
  $("c-plot").replaceChildren(plotParameters(series, {}));
}

// --------------------------------------------------------------------------------- library
async function libraryView() {
  mount("tpl-library");
  const d = await api("/api/library");
  const rows = d.materials.map((m) => el("tr", {},
    el("td", {}, el("a", {href: `#/library/${encodeURIComponent(m.name)}`}, m.name)), el("td", {}, m.members),
    el("td", {}, m.combination), el("td", {}, m.thicknesses_mm.map((t) => `${t} mm`).join(" + ")),
    el("td", {}, m.disagreeing_bins ? el("span", {class: "flag"}, `${m.disagreeing_bins} bins`) : el("span", {class: "clean"}, "none")),
    el("td", {}, m.tags.join(", ")), el("td", {}, m.created_utc.replace("T", " ").slice(0, 19))));
  $("materials").replaceChildren(...(rows.length ? rows
    : [el("tr", {}, el("td", {colspan: 7}, `No materials yet in ${d.library}.`))]));
}

async function materialView(name) {
  mount("tpl-material");
  const d = await api(`/api/library/${encodeURIComponent(name)}`);
  $("l-title").textContent = d.name;
  const fact = (k, v) => el("div", {}, el("b", {}, k), v);
  $("l-facts").replaceChildren(fact("Combined", d.combination.method),
    fact("Thickness", d.combination.thicknesses_mm.map((t) => `${t} mm`).join(" + ")),
    fact("Members", `${d.members.length}${d.origin === "imported" ? " (imported: provenance only)" : ""}`),
    fact("Tags", d.tags.join(", ") || "—"), fact("Created", d.created_utc.replace("T", " ").slice(0, 19)),
    ...(d.notes ? [fact("Notes", d.notes)] : []));
  const s = d.spectra;
  const spread = {wavelength_nm: s.wavelength_nm};
  for (const k of ["alpha", "sigma_t", "g"]) { spread[k] = s[k]; spread[`${k}_std`] = s[`${k}_spread`]; }
  const series = [{params: spread, color: "#8a93a0", band: true, name: "± spread between repeats"},
    {params: s, color: COLORS[0], band: true, name: "combined ± std"},
    ...d.members.filter((m) => m.here).map((m, i) => ({params: m.parameters, color: COLORS[1 + (i % 3)],
      dashed: true, name: m.measurement}))];
  $("l-legend").replaceChildren(...series.map((q) => el("span", {}, swatch(q.color), q.name)));
  $("l-plot").replaceChildren(plotParameters(series, {}));
  const disagree = s.flags.filter((f) => f & 1).length;
  $("l-problems").replaceChildren(
    ...(disagree ? [el("div", {class: "advice"}, `The repeats disagree beyond their stds in ${disagree} of ` +
      `${s.flags.length} bins (χ² p < ${d.combination.disagree_p}): the spread, not the std, is the uncertainty there.`)] : []),
    ...d.member_problems.map((p) => el("div", {class: "advice"}, `Member ${p}.`)));
  $("l-members").replaceChildren(...d.members.map((m) => el("tr", {},
    el("td", {}, m.here ? swatch(COLORS[1 + (d.members.filter((q) => q.here).indexOf(m) % 3)]) : ""),
    el("td", {}, m.here ? el("a", {href: `#/m/${encodeURIComponent(m.measurement)}`}, m.measurement) : m.measurement),
    el("td", {}, m.thicknesses_mm.map((t) => `${t} mm`).join(" + ")), el("td", {}, m.method),
    el("td", {}, m.maps.join(", ")), el("td", {}, m.here ? "yes" : el("span", {class: "flag"}, "missing")))));
}

// ------------------------------------------------------------------- Fig.-10-style plot (SVG)
const SVG = "http://www.w3.org/2000/svg";
function svg(tag, attrs = {}, ...children) {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  for (const c of children) node.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return node;
}

function plotParameters(series, {beer}) {
  const panels = [["alpha", "albedo α", [0, 1]], ["sigma_t", "extinction σt [1/mm]", null], ["g", "anisotropy g", [-1, 1]]];
  const W = 360, H = 250, M = {l: 46, r: 10, t: 22, b: 34};
  const root = svg("svg", {viewBox: `0 0 ${3 * W} ${H}`, role: "img"});
  panels.forEach(([key, title, fixed], i) => {
    const g = svg("g", {transform: `translate(${i * W},0)`});
    const wl = series[0].params.wavelength_nm;
    const x0 = Math.min(...wl), x1 = Math.max(...wl);
    let lo = fixed ? fixed[0] : 0, hi = fixed ? fixed[1] : 0;
    if (!fixed) {
      const values = series.flatMap((s) => s.params[key]).concat(beer ? beer.sigma_t_beer : [])
        .filter((v) => v !== null && Number.isFinite(v)).sort((p, q) => p - q);
      hi = values.length ? 1.15 * values[Math.floor(0.99 * (values.length - 1))] : 1;
      if (!(hi > 0)) hi = 1;
    }
    const X = (v) => M.l + (v - x0) / (x1 - x0 || 1) * (W - M.l - M.r);
    const Y = (v) => H - M.b - (Math.min(Math.max(v, lo), hi) - lo) / (hi - lo) * (H - M.t - M.b);
    for (let k = 0; k <= 4; k++) {
      const v = lo + (hi - lo) * k / 4;
      g.append(svg("line", {class: "grid", x1: M.l, x2: W - M.r, y1: Y(v), y2: Y(v)}),
        svg("text", {x: M.l - 6, y: Y(v) + 4, "text-anchor": "end"}, Math.abs(hi - lo) >= 10 ? v.toFixed(0) : v.toFixed(2)));
    }
    for (let k = 0; k <= 4; k++) {
      const v = x0 + (x1 - x0) * k / 4;
      g.append(svg("text", {x: X(v), y: H - M.b + 16, "text-anchor": "middle"}, v.toFixed(0)));
    }
    g.append(svg("line", {class: "axis", x1: M.l, x2: M.l, y1: M.t, y2: H - M.b}),
      svg("line", {class: "axis", x1: M.l, x2: W - M.r, y1: H - M.b, y2: H - M.b}),
      svg("text", {class: "title", x: (W + M.l) / 2, y: 14, "text-anchor": "middle"}, title),
      svg("text", {x: (W + M.l) / 2, y: H - 4, "text-anchor": "middle"}, "wavelength [nm]"));
    const path = (xs, ys) => {
      let d = "", pen = false;
      xs.forEach((x, j) => {
        const y = ys[j];
        if (y === null || !Number.isFinite(y)) { pen = false; return; }
        d += `${pen ? "L" : "M"}${X(x).toFixed(1)},${Y(y).toFixed(1)}`; pen = true;
      });
      return d;
    };
    for (const s of series) {
      const v = s.params[key], sd = s.params[`${key}_std`];
      if (s.band && sd) {
        const ok = v.map((y, j) => y !== null && sd[j] !== null && Number.isFinite(y) && Number.isFinite(sd[j]));
        const xs = s.params.wavelength_nm.filter((_, j) => ok[j]);
        const up = v.filter((_, j) => ok[j]).map((y, j) => y + sd.filter((_, q) => ok[q])[j]);
        const dn = v.filter((_, j) => ok[j]).map((y, j) => y - sd.filter((_, q) => ok[q])[j]);
        if (xs.length) {
          const d = path(xs, up) + path(xs.slice().reverse(), dn.slice().reverse()).replace(/^M/, "L") + "Z";
          g.append(svg("path", {d, fill: s.color, "fill-opacity": 0.15, stroke: "none"}));
        }
      }
      g.append(svg("path", {d: path(s.params.wavelength_nm, v), fill: "none", stroke: s.color,
        "stroke-width": s.dashed ? 1.2 : 2.2, "stroke-dasharray": s.dashed ? "5 4" : "none"}));
    }
    if (key === "sigma_t" && beer) {
      g.append(svg("path", {d: path(beer.wavelength_nm, beer.sigma_t_beer), fill: "none", stroke: "#c53030",
        "stroke-width": 1.2, "stroke-dasharray": "2 3"}));
      g.append(svg("text", {x: W - M.r - 4, y: M.t + 12, "text-anchor": "end", fill: "#c53030"}, "··· Beer's law"));
    }
    root.append(g);
  });
  return root;
}

// --------------------------------------------------------------------------------- router
async function route() {
  const parts = location.hash.replace(/^#\/?/, "").split("/").filter(Boolean);
  try {
    if (parts[0] === "history") await historyView();
    else if (parts[0] === "m" && parts[1]) await measurementView(decodeURIComponent(parts[1]));
    else if (parts[0] === "compare" && parts.length === 3) await compareView(parts[1], parts[2]);
    else if (parts[0] === "library" && parts[1]) await materialView(decodeURIComponent(parts[1]));
    else if (parts[0] === "library") await libraryView();
    else await homeView();
  } catch (e) {
    $("view").replaceChildren(el("section", {class: "card"}, el("p", {class: "msg error"}, e.message)));
  }
}
window.addEventListener("hashchange", route);
connectEvents();
route();
