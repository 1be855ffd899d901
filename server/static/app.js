// EvoColony dashboard: plain JS over the REST API (docs/api.md, docs/robots.md) and the
// server-sent events of GET /api/events (docs/dashboard.md). No build step, no framework.
"use strict";

const state = {
  runs: new Map(), // id -> RunOut
  selected: null, // run id
  gens: [[], [], [], []], // generation, best, mean, worst of the selected run
  source: null, // EventSource
  chart: null,
  cards: new Map(), // robot id -> card elements
  figuresFor: null, // "run:generation" the figures were last asked for
  championFor: null, // id of the completed run whose champion is shown
  checked: new Set(), // run ids whose best-fitness curves the overlay shows
  overlay: null, // uPlot of the checked runs
  studies: new Map(), // id -> StudyOut
  study: null, // id of the study shown
  studyChart: null, // uPlot of its conditions' curves
  studyKey: null, // its conditions, "\n"-joined: the chart is rebuilt when they change
  studiesTimer: null,
  archive: null, // {run, generation, axes, cells} of the selected QD run
  archiveFor: null, // "run:generation" the archive was last asked for
  archiveAt: 0, // when (ms): a live run's archive is replayed by the server, ask at most every 5 s
  picked: null, // index of the picked elite
  map: null, // GET /api/colony/map: the maze and each robot's pose, path and stuck marks
  mapTimer: null,
  chosen: new Set(), // robot ids ticked for a group push
  robot: null, // id of the robot whose panel is open
  robotChart: null, // its whisker and motor timeline (uPlot)
};
const MAP_POLL_MS = 1000;
const ROBOT_POLL_MS = 2000;
const TIMELINE_SAMPLES = 600; // one minute at 10 Hz

// Strategies whose runs keep an archive (docs/strategies.md).
const ARCHIVE_ROWS = 12; // the fittest elites listed beside the map

// Colours of the overlaid curves (a condition or a run each), cycled.
const PALETTE = ["#1f5fbf", "#b3261e", "#1e7d3a", "#b26b00", "#6a3fb5", "#00838f", "#5d4037", "#c2185b"];
function alpha(hex, a) {
  const n = parseInt(hex.slice(1), 16);
  return `rgba(${(n >> 16) & 255}, ${(n >> 8) & 255}, ${n & 255}, ${a})`;
}

const $ = (selector, root = document) => root.querySelector(selector);

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (key === "class") node.className = value;
    else if (key === "text") node.textContent = value;
    else node.setAttribute(key, value);
  }
  node.append(...children);
  return node;
}

// The server's bearer token (docs/security.md), kept in this browser only.
const TOKEN_KEY = "evocolony.token";
const token = () => localStorage.getItem(TOKEN_KEY) || "";
// EventSource and <img> cannot send headers: they pass the token as ?access_token=.
function withToken(path) {
  if (!token()) return path;
  return `${path}${path.includes("?") ? "&" : "?"}access_token=${encodeURIComponent(token())}`;
}

async function api(method, path, body) {
  const init = { method, headers: {} };
  if (token()) init.headers.Authorization = `Bearer ${token()}`;
  if (body !== undefined) {
    init.headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(path, init);
  const data = await response.json().catch(() => ({}));
  if (response.status === 401) $("#token").classList.add("needed");
  if (!response.ok) throw new Error(data.detail || `${response.status} ${response.statusText}`);
  return data;
}

const fmt = (x, digits = 3) => (x === null || x === undefined ? "–" : Number(x).toFixed(digits));
const short = (sha) => (sha ? sha.slice(0, 12) : "none");

// A time from the API as Unix seconds: a number already, or an ISO 8601 string.
function unixSeconds(value) {
  if (value === null || value === undefined) return null;
  return typeof value === "number" ? value : Date.parse(value) / 1000;
}

function ago(value) {
  const seconds = unixSeconds(value);
  if (seconds === null || Number.isNaN(seconds)) return "never";
  const s = Math.max(0, Date.now() / 1000 - seconds);
  if (s < 90) return `${Math.round(s)} s ago`;
  if (s < 5400) return `${Math.round(s / 60)} min ago`;
  return `${Math.round(s / 3600)} h ago`;
}

// ---- tabs ----------------------------------------------------------------------------------

function showTab() {
  const [tab, arg] = (location.hash || "#runs").slice(1).split("/");
  for (const section of document.querySelectorAll(".tab")) {
    section.hidden = section.id !== `tab-${tab}`;
  }
  for (const link of document.querySelectorAll("nav a")) {
    link.classList.toggle("active", link.dataset.tab === tab);
  }
  if (tab === "runs") resizeChart();
  clearInterval(state.studiesTimer);
  state.studiesTimer = null;
  clearInterval(state.mapTimer);
  state.mapTimer = null;
  if (tab === "colony") {
    loadMap();
    state.mapTimer = setInterval(loadMap, MAP_POLL_MS);
  }
  if (tab === "studies") {
    const id = Number(arg);
    if (Number.isInteger(id) && id > 0) state.study = id;
    loadStudies();
    state.studiesTimer = setInterval(loadStudies, STUDIES_POLL_MS);
  }
}

// ---- event stream --------------------------------------------------------------------------

function connect() {
  if (state.source) state.source.close();
  const query = state.selected === null ? "" : `?run=${state.selected}`;
  const source = new EventSource(withToken(`/api/events${query}`));
  state.source = source;
  const link = $("#link");
  source.onopen = () => {
    link.textContent = "live";
    link.classList.add("live");
  };
  source.onerror = () => {
    // Each stream ends after a few seconds and reopens at once; only a longer gap is news.
    setTimeout(() => {
      if (source.readyState !== EventSource.OPEN) {
        link.textContent = "reconnecting";
        link.classList.remove("live");
      }
    }, 2500);
  };
  source.addEventListener("run", (e) => onRun(JSON.parse(e.data)));
  source.addEventListener("generation", (e) => onGeneration(JSON.parse(e.data)));
  source.addEventListener("workers", (e) => renderWorkers(JSON.parse(e.data)));
  source.addEventListener("robots", (e) => renderRobots(JSON.parse(e.data)));
}

// ---- runs ----------------------------------------------------------------------------------

function onRun(run) {
  state.runs.set(run.id, run);
  if (state.selected === null && run.status === "running") {
    selectRun(run.id); // open on a run that is evolving now
    return;
  }
  renderRunsTable();
  if (run.id === state.selected) renderRunDetail();
  for (const card of state.cards.values()) fillRunChoices(card.runSelect);
  fillRunChoices($("#group-run"));
}

const networkName = (c) => (typeof c.network === "string" ? c.network : "custom");
const mazeName = (c) => (c.maze.includes("\n") ? "custom" : c.maze);

function studyLabel(run) {
  if (run.study_id === null || run.study_id === undefined) return "";
  const study = state.studies.get(run.study_id);
  return `${study ? study.name : `#${run.study_id}`}${run.condition ? ` / ${run.condition}` : ""}`;
}

// A champion's held-out roaming as "nominal / gap"; "–" before the run has one.
function championRoaming(champion) {
  if (!champion || !champion.test) return "–";
  const t = champion.test;
  return `${fmt(100 * t.nominal.roaming.value, 0)} % / ${fmt(100 * t.gap.roaming.value, 0)} %`;
}

function renderRunsTable() {
  const body = $("#runs-table tbody");
  const runs = [...state.runs.values()].sort((a, b) => b.id - a.id);
  body.replaceChildren(
    ...runs.map((run) => {
      const box = el("input", {
        type: "checkbox", "aria-label": `overlay run ${run.id}`, "data-testid": `check-${run.id}`,
      });
      box.checked = state.checked.has(run.id);
      box.addEventListener("click", (e) => e.stopPropagation());
      box.addEventListener("change", () => {
        if (box.checked) state.checked.add(run.id);
        else state.checked.delete(run.id);
        renderOverlayBar();
      });
      const row = el(
        "tr",
        { "data-run": run.id },
        el("td", {}, box),
        el("td", { text: run.id }),
        el("td", { class: "name", text: run.name || "", title: run.name || "" }),
        el("td", { text: networkName(run.config) }),
        el("td", { text: mazeName(run.config) }),
        el("td", { text: run.seed }),
        el("td", { class: "study", text: studyLabel(run), title: studyLabel(run) }),
        el("td", {}, el("span", { class: `status ${run.status}`, text: run.status })),
        el("td", { class: "whole", text: `${run.generation} / ${run.generations}` }),
        el("td", { text: fmt(run.best_fitness_so_far) }),
        el("td", { class: "whole", text: championRoaming(run.champion) }),
      );
      if (run.id === state.selected) row.classList.add("selected");
      row.addEventListener("click", () => selectRun(run.id));
      return row;
    }),
  );
}

function selectRun(id) {
  if (state.selected === id) return;
  state.selected = id;
  state.gens = [[], [], [], []];
  state.figuresFor = null;
  state.championFor = null;
  $("#run-validation").hidden = true;
  for (const img of [$("#network-img"), $("#paths-img")]) img.hidden = true;
  updateChart();
  renderRunsTable();
  renderRunDetail();
  connect(); // a stream of this run's generations, from the first
}

function renderRunDetail() {
  const run = state.runs.get(state.selected);
  $("#run-empty").hidden = Boolean(run);
  $("#run-body").hidden = !run;
  if (!run) return;
  const c = run.config;
  $("#run-title").textContent = run.name ? `Run ${run.id}: ${run.name}` : `Run ${run.id}`;
  const status = $("#run-status");
  status.textContent = run.status;
  status.className = `status ${run.status}`;
  $("#run-meta").textContent =
    `seed ${run.seed} · population ${c.population} · ${c.trials} trials × ${run.trial_steps} steps · ` +
    `network ${networkName(c)} · maze ${mazeName(c)} · strategy ${c.strategy} · ` +
    `generation ${run.generation}/${run.generations} · ${run.evaluations} evaluations` +
    (run.generation > 0
      ? ` · training fitness: best so far ${fmt(run.best_fitness_so_far)}, ` +
        `last generation's best ${fmt(run.best_fitness)}`
      : "");
  const [network, paths] = run.champion
    ? ["Champion's network", "Champion's paths"]
    : ["Network of the last generation's best", "Paths of the last generation's best"];
  $("#network-caption").textContent = `${network}: whiskers in, wheels out (line width ~ |w|)`;
  $("#paths-caption").textContent = `${paths} from unseen start poses (click: full size)`;
  const error = $("#run-error");
  error.hidden = !run.error;
  error.textContent = run.error || "";
  const allowed = {
    pause: ["queued", "running"],
    resume: ["paused"],
    cancel: ["queued", "running", "paused"],
  };
  for (const button of document.querySelectorAll("#run-body .controls button")) {
    button.disabled = !allowed[button.dataset.action].includes(run.status);
  }
  refreshFigures(run);
  showChampion(run);
  showArchive(run);
}

// ---- archive of a quality-diversity run -----------------------------------------------------

async function showArchive(run) {
  const panel = $("#archive");
  if (!run.keeps_archive || run.generation < 1) {
    panel.hidden = true;
    return;
  }
  const key = `${run.id}:${run.generation}`;
  const sameRun = state.archive && state.archive.run === run.id;
  const live = !["completed", "failed", "cancelled"].includes(run.status);
  if (state.archiveFor === key || (sameRun && live && Date.now() - state.archiveAt < 5000)) return;
  state.archiveFor = key;
  state.archiveAt = Date.now();
  if (!sameRun) state.picked = null;
  try {
    const archive = await api("GET", `/api/runs/${run.id}/archive`);
    if (state.selected !== run.id) return;
    state.archive = { run: run.id, ...archive };
    if (state.picked !== null && state.picked >= archive.cells.length) state.picked = null;
    panel.hidden = false;
    renderArchive();
  } catch {
    state.archiveFor = null; // asked again with the next run event
  }
}

function fitnessColour(f, lo, hi) {
  if (f === null) return "#999";
  const t = hi > lo ? (f - lo) / (hi - lo) : 1;
  return `hsl(${Math.round(240 * (1 - t))}, 70%, 45%)`;
}

function renderArchive() {
  const a = state.archive;
  const [xName, yName] = a.axes;
  $("#archive-title").textContent =
    `Archive: ${a.cells.length} elites after ${a.generation} generations ` +
    `(${xName} × ${yName}, colour: training fitness)`;
  $("#archive-x").textContent = xName;
  $("#archive-y").textContent = yName;
  const canvas = $("#archive-map");
  canvas.dataset.elites = String(a.cells.length);
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const known = a.cells.map((c) => c.fitness).filter((f) => f !== null);
  const lo = Math.min(...known);
  const hi = Math.max(...known);
  a.cells.forEach((c, k) => {
    const [x, y] = elitePoint(c, canvas);
    ctx.fillStyle = fitnessColour(c.fitness, lo, hi);
    ctx.beginPath();
    ctx.arc(x, y, k === state.picked ? 6 : 4, 0, 2 * Math.PI);
    ctx.fill();
    if (k === state.picked) {
      ctx.strokeStyle = "#000";
      ctx.stroke();
    }
  });
  const order = a.cells.map((_, k) => k).sort((i, j) => (a.cells[j].fitness ?? -Infinity) - (a.cells[i].fitness ?? -Infinity));
  const rows = order.slice(0, ARCHIVE_ROWS);
  if (state.picked !== null && !rows.includes(state.picked)) rows.push(state.picked);
  $("#archive-table tbody").replaceChildren(
    ...rows.map((k) => {
      const c = a.cells[k];
      const row = el("tr", { "data-elite": String(k), class: k === state.picked ? "picked" : "" },
        el("td", { text: String(k) }),
        el("td", { text: fmt(c.descriptors[0]) }),
        el("td", { text: fmt(c.descriptors[1]) }),
        el("td", { text: fmt(c.fitness) }),
        el("td", {}, el("code", { text: short(c.sha256) })));
      row.addEventListener("click", () => pickElite(k));
      return row;
    }),
  );
  fillArchiveRobots();
}

function elitePoint(cell, canvas) {
  return [cell.descriptors[0] * canvas.width, (1 - cell.descriptors[1]) * canvas.height];
}

function pickElite(k) {
  state.picked = k;
  const c = state.archive.cells[k];
  const message = $("#archive-message");
  message.textContent = `elite ${k}: fitness ${fmt(c.fitness)}, controller ${short(c.sha256)}`;
  message.className = "message";
  renderArchive();
}

function onArchiveClick(event) {
  // The elite nearest the click, if within 8 px.
  if (!state.archive) return;
  const canvas = $("#archive-map");
  const box = canvas.getBoundingClientRect();
  const x = (event.clientX - box.left) * (canvas.width / box.width);
  const y = (event.clientY - box.top) * (canvas.height / box.height);
  let best = null;
  let bestD = 64.5; // (8 px)^2, inclusive
  state.archive.cells.forEach((c, k) => {
    const [px, py] = elitePoint(c, canvas);
    const d = (px - x) ** 2 + (py - y) ** 2;
    if (d < bestD) [best, bestD] = [k, d];
  });
  if (best !== null) pickElite(best);
}

function fillArchiveRobots() {
  const select = $("#archive-robot");
  const current = select.value;
  const ids = [...state.cards.keys()].sort();
  select.replaceChildren(...ids.map((id) => el("option", { value: id, text: id })));
  if (ids.includes(current)) select.value = current;
  $("#archive-push").disabled = state.picked === null || ids.length === 0;
}

async function pushElite() {
  const robot = $("#archive-robot").value;
  if (state.picked === null || !robot) return;
  const body = { run_id: state.archive.run, elite: state.picked };
  await sendPush(robot, body, $("#archive-push"), $("#archive-message"));
}

function showChampion(run) {
  // A completed run's champion (RunOut.champion): its held-out test, then how it was chosen.
  const c = run.champion;
  if (!c || state.championFor === run.id) return;
  state.championFor = run.id;
  const line = $("#run-validation");
  const v = c.validation;
  const chosen = v
    ? `chosen on validation ${fmt(v.score)} over ${v.poses} poses × ${v.steps} steps ` +
      `(training fitness ${fmt(c.training_fitness)}, rank ${v.training_rank})`
    : `training rank 0 (validation off; training fitness ${fmt(c.training_fitness)})`;
  const t = c.test;
  const pct = (p) => `${fmt(100 * p.value, 0)} % [${fmt(100 * p.low, 0)}, ${fmt(100 * p.high, 0)}]`;
  const world = (label, w) => `${label}: roaming ${pct(w.roaming)}, stuck ${pct(w.stuck)}`;
  line.textContent = `Champion ${short(c.sha256)}: ` + (t
    ? `held-out test on ${t.poses} unseen poses × ${t.steps} steps (95 % CI) · ` +
      `${world("under the reality gap", t.gap)} · ${world("nominal", t.nominal)} · ${chosen}`
    : chosen);
  line.hidden = false;
  showRobustness(run.id, c.sha256);
}

async function showRobustness(runId, sha) {
  // The champion's roaming per whisker range x wheel gain ratio (GET .../robustness, cached).
  const box = $("#run-robustness");
  box.hidden = true;
  let m;
  try {
    m = await api("GET", `/api/controllers/${sha}/robustness`);
  } catch {
    return; // the map is extra: the run page stands without it
  }
  if (state.selected !== runId) return;
  const table = $("#robustness-table");
  table.replaceChildren(
    el("tr", {}, el("th", { text: "whisker \\ L/R gain" }),
      ...m.gain_ratios.map((r) => el("th", { text: fmt(r, 2) }))),
  );
  for (let i = m.whisker_ranges.length - 1; i >= 0; i--) {
    const cells = m.roaming[i].map((v, j) => {
      const td = el("td", { text: `${fmt(100 * v, 0)}` });
      td.style.background = `hsl(${Math.round(120 * v)}, 60%, 38%)`;
      td.title = `roaming ${fmt(100 * v, 0)} %, stuck ${fmt(100 * m.stuck[i][j], 0)} %`;
      return td;
    });
    table.append(el("tr", {}, el("th", { text: `${fmt(1000 * m.whisker_ranges[i], 1)} mm` }), ...cells));
  }
  const worst = Math.min(...m.roaming.flat());
  $("#robustness-caption").textContent =
    `roaming, % of ${m.poses} unseen poses × ${m.steps} steps per cell (hover: stuck); ` +
    `worst cell ${fmt(100 * worst, 0)} %`;
  box.hidden = false;
}

async function steer(action) {
  if (state.selected === null) return;
  try {
    onRun(await api("POST", `/api/runs/${state.selected}/${action}`));
  } catch (err) {
    const error = $("#run-error");
    error.hidden = false;
    error.textContent = `${action}: ${err.message}`;
  }
}

// A figure at full size (as large as the window allows) in a modal; a click or Esc closes it.
function zoom(img) {
  if (img.hidden || !img.src) return;
  const big = $("#zoom-img");
  big.src = img.src;
  big.alt = img.alt;
  $("#zoom").showModal();
}

function refreshFigures(run) {
  // The server answers 304 until the best controller changes (ETag = its sha256).
  if (run.generation < 1) return;
  const key = `${run.id}:${run.generation}`;
  if (state.figuresFor === key) return;
  state.figuresFor = key;
  for (const [id, figure] of [["#network-img", "network"], ["#paths-img", "paths"]]) {
    const img = $(id);
    if (img.dataset.loading === "1") continue; // the next generation asks again
    const next = new Image();
    img.dataset.loading = "1";
    next.onload = () => {
      img.src = next.src;
      img.hidden = false;
      img.dataset.loading = "";
    };
    next.onerror = () => {
      img.dataset.loading = "";
    };
    next.src = withToken(`/api/runs/${run.id}/best/${figure}.png?g=${run.generation}`);
  }
}

// ---- fitness curve -------------------------------------------------------------------------

function makeChart() {
  const target = $("#curve");
  state.chart = new uPlot(
    {
      width: Math.max(300, target.clientWidth || 800),
      height: 300,
      scales: { x: { time: false } },
      axes: [{ label: "generation" }, { label: "training fitness (Eq 12)" }],
      series: [
        { label: "generation" },
        { label: "best of generation", stroke: "#1f5fbf", width: 2 },
        { label: "mean", stroke: "#444", width: 1.5, dash: [6, 4] },
        { label: "worst", stroke: "#b3261e", width: 1, dash: [2, 3] },
      ],
    },
    state.gens,
    target,
  );
}

function onGeneration(g) {
  if (g.run_id !== state.selected) return;
  const xs = state.gens[0];
  if (xs.length && g.generation <= xs[xs.length - 1]) return; // a replay after reconnecting
  xs.push(g.generation);
  state.gens[1].push(g.best);
  state.gens[2].push(g.mean);
  state.gens[3].push(g.worst);
  updateChart();
}

function updateChart() {
  state.chart.setData(state.gens);
  $("#curve").dataset.points = String(state.gens[0].length);
}

function resizeChart() {
  const width = $("#curve").clientWidth;
  if (state.chart && width > 0) state.chart.setSize({ width, height: 300 });
}

// ---- overlay of several runs ----------------------------------------------------------------

function renderOverlayBar() {
  const n = state.checked.size;
  const button = $("#overlay-button");
  button.disabled = n < 2;
  button.textContent = n < 2 ? "Overlay checked runs" : `Overlay ${n} runs`;
}

async function showOverlay() {
  const ids = [...state.checked].sort((a, b) => a - b);
  const message = $("#overlay-message");
  message.textContent = "loading…";
  try {
    const rows = await Promise.all(ids.map((id) => api("GET", `/api/runs/${id}/generations`)));
    const curves = rows.map((gens) => new Map(gens.map((g) => [g.generation, g.best])));
    const series = ids.map((id, i) => {
      const run = state.runs.get(id);
      return { label: run && run.name ? `${id} ${run.name}` : `run ${id}`, stroke: PALETTE[i % PALETTE.length], width: 2 };
    });
    const target = $("#overlay-curve");
    $("#overlay-panel").hidden = false;
    if (state.overlay) state.overlay.destroy();
    state.overlay = new uPlot(
      {
        width: Math.max(300, target.clientWidth || 800),
        height: 300,
        scales: { x: { time: false } },
        axes: [{ label: "generation" }, { label: "best of generation (training fitness)" }],
        series: [{ label: "generation" }, ...series],
      },
      aligned(curves),
      target,
    );
    target.dataset.series = String(ids.length);
    message.textContent = "";
  } catch (err) {
    message.textContent = err.message;
  }
}

// uPlot data from several curves (Map x -> y): their x values joined, null where one has none.
function aligned(curves) {
  const xs = [...new Set(curves.flatMap((c) => [...c.keys()]))].sort((a, b) => a - b);
  return [xs, ...curves.map((c) => xs.map((x) => (c.has(x) ? c.get(x) : null)))];
}

// ---- studies -------------------------------------------------------------------------------

const STUDIES_POLL_MS = 2000; // while the Studies page is open; studies change at run pace

async function loadStudies() {
  try {
    const studies = await api("GET", "/api/studies");
    state.studies = new Map(studies.map((s) => [s.id, s]));
  } catch {
    return; // the next tick asks again (the token may be missing)
  }
  renderStudiesTable();
  renderStudy();
  renderRunsTable(); // study names in the runs' study column
}

const doneRuns = (study) =>
  study.runs.filter((r) => ["completed", "failed", "cancelled"].includes(r.status)).length;

function renderStudiesTable() {
  $("#studies-empty").hidden = state.studies.size > 0;
  $("#studies-table tbody").replaceChildren(
    ...[...state.studies.values()].map((study) => {
      const row = el(
        "tr",
        { "data-study": study.id },
        el("td", { text: study.id }),
        el("td", { text: study.name }),
        el("td", {}, el("span", { class: `status ${study.status}`, text: study.status })),
        el("td", { text: `${doneRuns(study)} / ${study.runs.length}` }),
      );
      if (study.id === state.study) row.classList.add("selected");
      row.addEventListener("click", () => {
        location.hash = `#studies/${study.id}`;
      });
      return row;
    }),
  );
}

function renderStudy() {
  const study = state.studies.get(state.study);
  $("#study-empty").hidden = Boolean(study);
  $("#study-body").hidden = !study;
  if (!study) return;
  $("#study-title").textContent = `Study ${study.id}: ${study.name}`;
  const status = $("#study-status");
  status.textContent = study.status;
  status.className = `status ${study.status}`;
  $("#study-cancel").disabled = study.status !== "running";
  const conditions = study.summary.map((s) => s.condition);
  $("#study-meta").textContent =
    `${conditions.length} condition${conditions.length === 1 ? "" : "s"} (${conditions.join(", ")}) · ` +
    `${study.seeds.length} seed${study.seeds.length === 1 ? "" : "s"} · ` +
    `runs done ${doneRuns(study)} / ${study.runs.length} · created ${new Date(study.created_at).toLocaleString()}`;
  renderStudyCurve(study);
  $("#verdicts").replaceChildren(...study.verdicts.map((v) => el("li", { text: v })));
  renderFinal(study);
  $("#comparisons-table tbody").replaceChildren(
    ...study.comparisons.map((c) =>
      el(
        "tr",
        {},
        el("td", { text: c.a }),
        el("td", { text: c.b }),
        el("td", { text: c.metric }),
        el("td", { text: pValue(c.p_holm), class: c.p_holm < 0.05 ? "significant" : "" }),
        el("td", { text: fmt(c.a12, 2) }),
      ),
    ),
  );
  $("#study-runs-table tbody").replaceChildren(
    ...study.runs.map((r) => {
      const row = el(
        "tr",
        { "data-run": r.run_id },
        el("td", { text: r.run_id }),
        el("td", { text: r.condition }),
        el("td", { text: r.seed }),
        el("td", {}, el("span", { class: `status ${r.status}`, text: r.status })),
        el("td", { text: fmt(r.metrics.best_fitness) }),
        el("td", { text: fmt(r.metrics.validation_score) }),
        el("td", { text: r.metrics.roaming === null || r.metrics.roaming === undefined ? "–" : `${fmt(100 * r.metrics.roaming, 0)} %` }),
      );
      row.addEventListener("click", () => openRun(r.run_id));
      return row;
    }),
  );
}

const pValue = (p) => (p === null || p === undefined ? "–" : p < 0.001 ? Number(p).toExponential(1) : fmt(p, 3));

function renderFinal(study) {
  // A row per metric, a column per condition: it fits however many metrics there are.
  const metrics = [...new Set(study.summary.flatMap((s) => Object.keys(s.final)))];
  $("#final-table thead tr").replaceChildren(
    el("th", { text: "metric" }), ...study.summary.map((s) => el("th", { text: s.condition })),
  );
  const cell = (v) => (v ? `${fmt(v.median)} [${fmt(v.ci_low)}, ${fmt(v.ci_high)}]` : "–");
  $("#final-table tbody").replaceChildren(
    el("tr", {}, el("td", { text: "completed runs" }),
      ...study.summary.map((s) => el("td", { text: `${s.completed} / ${s.runs}` }))),
    ...metrics.map((m) =>
      el("tr", {}, el("td", { text: m }), ...study.summary.map((s) => el("td", { text: cell(s.final[m]) })))),
  );
}

// Per condition three series (median, CI low, CI high) and a band between the last two.
function renderStudyCurve(study) {
  const target = $("#study-curve");
  const summaries = study.summary;
  const curves = summaries.flatMap((s) => {
    const at = (key) => new Map(s.generations.map((g) => [g.generation, g.best[key]]));
    return [at("median"), at("ci_low"), at("ci_high")];
  });
  const data = aligned(curves);
  const key = `${study.id}\n${summaries.map((s) => s.condition).join("\n")}`;
  if (state.studyChart && state.studyKey === key) {
    state.studyChart.setData(data);
  } else {
    if (state.studyChart) state.studyChart.destroy();
    state.studyKey = key;
    const series = [{ label: "generation" }];
    const bands = [];
    summaries.forEach((s, i) => {
      const color = PALETTE[i % PALETTE.length];
      const first = series.length;
      series.push(
        { label: s.condition, stroke: color, width: 2 },
        { label: `${s.condition} CI low`, stroke: alpha(color, 0.35), width: 1 },
        { label: `${s.condition} CI high`, stroke: alpha(color, 0.35), width: 1 },
      );
      bands.push({ series: [first + 2, first + 1], fill: alpha(color, 0.15) });
    });
    state.studyChart = new uPlot(
      {
        width: Math.max(300, target.clientWidth || 800),
        height: 320,
        scales: { x: { time: false } },
        axes: [{ label: "generation" }, { label: "best of generation (training fitness)" }],
        series,
        bands,
        legend: { live: false },
      },
      data,
      target,
    );
    // The legend names each condition once: its median's entry (the band's are hidden).
    const entries = state.studyChart.root.querySelectorAll(".u-legend .u-series");
    const skipped = series.length - entries.length; // a legend that is not live omits x
    entries.forEach((entry, i) => {
      const index = i + skipped;
      entry.hidden = index === 0 || (index - 1) % 3 !== 0;
    });
  }
  target.dataset.series = String(summaries.length);
  target.dataset.points = String(data[0].length);
}

async function openRun(id) {
  // A study's run may be older than the newest 100 the stream follows: ask for it.
  try {
    onRun(await api("GET", `/api/runs/${id}`));
  } catch {
    // the stream brings it if it can
  }
  location.hash = "#runs";
  selectRun(id);
}

async function cancelStudy() {
  if (state.study === null) return;
  try {
    const study = await api("POST", `/api/studies/${state.study}/cancel`);
    state.studies.set(study.id, study);
    renderStudiesTable();
    renderStudy();
  } catch (err) {
    $("#study-meta").textContent = `cancel: ${err.message}`;
  }
}

// ---- colony --------------------------------------------------------------------------------

function fillRunChoices(select) {
  const chosen = select.value;
  const runs = [...state.runs.values()].filter((r) => r.generation > 0).sort((a, b) => b.id - a.id);
  select.replaceChildren(
    ...runs.map((r) => el("option", { value: r.id, text: `run ${r.id} (${r.status})` })),
  );
  if (runs.some((r) => String(r.id) === chosen)) select.value = chosen;
}

function makeCard(id) {
  const field = (name) => el("dd", { "data-field": name });
  const dl = el("dl");
  for (const [label, name] of [
    ["state", "state"],
    ["controller", "controller"],
    ["origin", "origin"],
    ["whiskers", "whiskers"],
    ["steps", "steps"],
    ["stuck events", "stuck"],
    ["field", "field"],
    ["physics", "physics"],
    ["stuck / h", "calibrated"],
    ["last seen", "seen"],
  ]) {
    dl.append(el("dt", { text: label }), field(name));
  }
  const runSelect = el("select", { "data-testid": `push-run-${id}`, "aria-label": "run" });
  const rank = el("input", {
    type: "number", min: "0", placeholder: "best", "data-testid": `push-rank-${id}`,
    "aria-label": "training rank (empty: the run's best)",
  });
  const button = el("button", { "data-testid": `push-${id}`, text: "Push" });
  const message = el("span", { class: "message", "data-testid": `push-result-${id}` });
  button.addEventListener("click", () => push(id, runSelect, rank, button, message));
  const pick = el("input", { type: "checkbox", "data-testid": `select-${id}`, "aria-label": `select ${id}` });
  pick.checked = state.chosen.has(id);
  pick.addEventListener("change", () => {
    if (pick.checked) state.chosen.add(id);
    else state.chosen.delete(id);
  });
  const policy = el("select", { "data-testid": `policy-${id}`, "aria-label": "replacement policy" },
    el("option", { value: "", text: "the colony's" }),
    ...["off", "rank", "archive", "fit"].map((p) => el("option", { value: p, text: p })));
  const policyMessage = el("span", { class: "message", "data-testid": `policy-result-${id}` });
  policy.addEventListener("change", () => setPolicy(id, policy, policyMessage));
  const details = el("button", { "data-testid": `details-${id}`, text: "Timeline" });
  details.addEventListener("click", () => openRobot(id));
  const card = el(
    "article",
    { class: "card", "data-robot": id },
    el("h3", {}, el("span", { class: "dot" }), el("span", { class: "swatch" }), el("span", { text: id }),
      el("label", { class: "pick" }, pick, " select")),
    dl,
    el("div", { class: "policy" }, el("span", { text: "when stuck" }), policy, policyMessage, details),
    el("div", { class: "push" }, el("span", { text: "push" }), runSelect, el("span", { text: "rank" }),
      rank, button, message),
  );
  fillRunChoices(runSelect);
  return { card, runSelect, policy };
}

async function setPolicy(id, select, message) {
  // PUT /api/robots/{id}/replacement: the robot's own policy, or null to follow the colony's.
  select.disabled = true;
  try {
    const robot = await api("PUT", `/api/robots/${encodeURIComponent(id)}/replacement`,
      { policy: select.value || null });
    message.textContent = `${robot.replacement} (${robot.replacement_source === "robot" ? "its own" : "the colony's"})`;
    message.className = "message ok";
  } catch (err) {
    message.textContent = err.message;
    message.className = "message bad";
  } finally {
    select.disabled = false;
  }
}

// ---- group push ----------------------------------------------------------------------------

async function groupPush() {
  const message = $("#group-message");
  const run = $("#group-run").value;
  if (!run) {
    message.replaceChildren(el("li", { class: "bad", text: "no run with a completed generation to push from" }));
    return;
  }
  const all = $("#group-target").value === "all";
  // "all": every robot online now; a selection is pushed as chosen (an offline one says so)
  const robots = [...state.cards.entries()]
    .filter(([id, entry]) => (all ? entry.online : state.chosen.has(id)))
    .map(([id]) => id);
  if (robots.length === 0) {
    message.replaceChildren(el("li", { class: "bad", text: all ? "no robot is online" : "no robot selected" }));
    return;
  }
  const body = { run_id: Number(run) };
  if ($("#group-rank").value !== "") body.rank = Number($("#group-rank").value);
  const button = $("#group-push");
  button.disabled = true;
  const lines = new Map(robots.map((id) => [id, el("li", { "data-robot": id, text: `${id}: pushing…` })]));
  message.replaceChildren(...lines.values());
  await Promise.all(robots.map(async (id) => {
    const line = lines.get(id);
    try {
      const reply = await api("POST", `/api/robots/${encodeURIComponent(id)}/controller`, body);
      const ok = reply.acknowledged && reply.accepted;
      line.textContent = ok
        ? `${id} acknowledged: running ${short(reply.sha256)}`
        : `${id}: ${reply.acknowledged ? `refused: ${reply.reason}` : "no acknowledgement"}`;
      line.className = ok ? "ok" : "bad";
    } catch (err) {
      line.textContent = `${id}: ${err.message}`;
      line.className = "bad";
    }
  }));
  button.disabled = false;
}

// ---- the map -------------------------------------------------------------------------------

function robotColour(id) {
  const ids = [...state.cards.keys()].sort();
  const i = ids.indexOf(id);
  return PALETTE[(i < 0 ? 0 : i) % PALETTE.length];
}

async function loadMap() {
  try {
    state.map = await api("GET", "/api/colony/map");
  } catch (err) {
    $("#map-legend").textContent = err.message;
    return;
  }
  drawMap();
}

function drawMap() {
  // The maze north up; robots' recent paths, their poses now, and stuck marks, in metres.
  const { maze, robots } = state.map;
  const canvas = $("#colony-map");
  const width = canvas.width;
  const scale = width / maze.width;
  const height = Math.round(maze.height * scale);
  if (canvas.height !== height) canvas.height = height;
  const at = (x, y) => [x * scale, height - y * scale];
  const g = canvas.getContext("2d");
  g.fillStyle = "#fff";
  g.fillRect(0, 0, width, height);
  g.fillStyle = "#3b4250";
  const cell = maze.cell_size * scale;
  maze.rows.forEach((row, r) => {
    [...row].forEach((c, i) => {
      if (c === "#") g.fillRect(i * cell, r * cell, Math.ceil(cell), Math.ceil(cell));
    });
  });
  $("#map-title").textContent = `Maze ${maze.name} (${fmt(maze.width, 1)} x ${fmt(maze.height, 1)} m)`;
  const positions = {};
  let stuck = 0;
  for (const robot of robots) {
    if (robot.pose === null) continue;
    const colour = robot.online ? robotColour(robot.id) : "#9aa3ad"; // offline: where it was last
    g.strokeStyle = alpha(colour, 0.55);
    g.lineWidth = 1.5;
    g.beginPath();
    robot.path.forEach(([x, y], i) => (i ? g.lineTo(...at(x, y)) : g.moveTo(...at(x, y))));
    g.stroke();
    g.strokeStyle = "#b3261e";
    g.lineWidth = 2;
    for (const mark of robot.stuck) {
      const [cx, cy] = at(mark.x, mark.y);
      g.beginPath();
      g.moveTo(cx - 5, cy - 5);
      g.lineTo(cx + 5, cy + 5);
      g.moveTo(cx + 5, cy - 5);
      g.lineTo(cx - 5, cy + 5);
      g.stroke();
      stuck += 1;
    }
    const [x, y, theta] = robot.pose;
    const [cx, cy] = at(x, y);
    g.fillStyle = colour;
    g.strokeStyle = colour;
    g.lineWidth = 2;
    g.beginPath();
    g.arc(cx, cy, 6, 0, 2 * Math.PI);
    if (robot.pose_source === "odometry") g.stroke();
    else g.fill();
    g.beginPath();
    g.moveTo(cx, cy);
    g.lineTo(cx + 12 * Math.cos(theta), cy - 12 * Math.sin(theta));
    g.stroke();
    g.fillStyle = "#1d2127";
    g.fillText(robot.id, cx + 9, cy - 8);
    positions[robot.id] = [Number(x.toFixed(4)), Number(y.toFixed(4))];
  }
  canvas.dataset.positions = JSON.stringify(positions);
  canvas.dataset.robots = String(Object.keys(positions).length);
  canvas.dataset.stuck = String(stuck);
}

// ---- one robot's panel ---------------------------------------------------------------------

function openRobot(id) {
  state.robot = id;
  $("#robot-panel").hidden = false;
  $("#robot-panel-title").textContent = `Robot ${id}`;
  if (state.robotChart) state.robotChart.destroy();
  state.robotChart = null;
  loadRobot();
  $("#robot-panel").scrollIntoView({ block: "nearest" });
}

function closeRobot() {
  state.robot = null;
  $("#robot-panel").hidden = true;
}

async function loadRobot() {
  const id = state.robot;
  if (id === null) return;
  const path = `/api/robots/${encodeURIComponent(id)}`;
  let traces, stuck;
  try {
    [traces, stuck] = await Promise.all([
      api("GET", `${path}/traces?limit=${TIMELINE_SAMPLES}`),
      api("GET", `${path}/stuck?limit=100`),
    ]);
  } catch (err) {
    $("#robot-stuck-empty").textContent = err.message;
    return;
  }
  if (state.robot !== id) return;
  const samples = traces.samples;
  const t0 = samples.length ? (samples[0].at ?? 0) : 0;
  const xs = samples.map((s, i) => (s.at === null ? i * 0.1 : s.at - t0));
  const data = [
    xs,
    samples.map((s) => s.motors[0]),
    samples.map((s) => s.motors[1]),
    samples.map((s) => [...s.whiskers].filter((b) => b === "1").length),
  ];
  const target = $("#robot-timeline");
  if (state.robotChart) state.robotChart.setData(data);
  else {
    state.robotChart = new uPlot(
      {
        width: Math.max(300, target.clientWidth || 800),
        height: 240,
        scales: { x: { time: false }, m: { range: [-1.05, 1.05] }, w: { range: [0, 5] } },
        axes: [
          { label: "seconds" },
          { label: "motor command", scale: "m" },
          { label: "whiskers touching", scale: "w", side: 1, grid: { show: false } },
        ],
        series: [
          { label: "s" },
          { label: "left motor", stroke: PALETTE[0], scale: "m" },
          { label: "right motor", stroke: PALETTE[1], scale: "m" },
          { label: "whiskers", stroke: PALETTE[3], scale: "w", paths: uPlot.paths.stepped({ align: 1 }) },
        ],
      },
      data,
      target,
    );
  }
  target.dataset.points = String(samples.length);
  $("#robot-stuck-empty").hidden = stuck.events.length > 0;
  $("#robot-stuck-table").hidden = stuck.events.length === 0;
  $("#robot-stuck-table tbody").replaceChildren(
    ...stuck.events.slice().reverse().map((e) =>
      el("tr", { "data-event": e.id },
        el("td", { text: new Date(unixSeconds(e.at) * 1000).toLocaleTimeString() }),
        el("td", { text: e.step }),
        el("td", { text: e.reason }),
        el("td", {}, el("code", { text: short(e.controller_sha256) })),
        el("td", { text: e.policy ?? "–" }),
        el("td", {}, el("code", { text: short(e.replacement_sha256) })),
        el("td", { text: e.answer ?? "" }),
        el("td", { text: e.steps_run ?? "–" }))),
  );
}

async function push(id, runSelect, rank, button, message) {
  if (!runSelect.value) {
    message.textContent = "no run with a completed generation to push from";
    message.className = "message bad";
    return;
  }
  const body = { run_id: Number(runSelect.value) }; // no rank: the run's best (champion)
  if (rank.value !== "") body.rank = Number(rank.value);
  await sendPush(id, body, button, message);
}

async function sendPush(robot, body, button, message) {
  // POST /api/robots/{id}/controller and show the robot's answer under the button.
  button.disabled = true;
  message.textContent = "pushing…";
  message.className = "message";
  try {
    const reply = await api("POST", `/api/robots/${encodeURIComponent(robot)}/controller`, body);
    const ok = reply.acknowledged && reply.accepted;
    message.textContent = ok
      ? `${robot} acknowledged: running ${short(reply.sha256)}`
      : reply.acknowledged
        ? `refused: ${reply.reason}`
        : `no acknowledgement ${reply.reason ? `(${reply.reason})` : ""}`;
    message.className = `message ${ok ? "ok" : "bad"}`;
  } catch (err) {
    message.textContent = err.message;
    message.className = "message bad";
  } finally {
    button.disabled = false;
  }
}

function whiskerBits(bits) {
  return el("span", { class: "whiskers", title: `whiskers ${bits} (left to right)` },
    ...[...bits].map((b) => el("span", { class: b === "1" ? "hit" : "" })));
}

function physics(fit) {
  // The robot's fitted physics (colony robot calibrate): whisker ranges in mm, wheel gains.
  if (fit === null) return "not calibrated";
  const mm = fit.whisker_range.map((r, i) => {
    const u = fit.uncertainty.whisker_range[i];
    // a whisker whose bit never changed is only known within an interval
    return fit.bounded.includes(i)
      ? `${Math.round(1000 * Math.max(0, r - u))}–${Math.round(1000 * (r + u))}`
      : String(Math.round(1000 * r));
  });
  return `whiskers ${mm.join(" ")} mm, gains ${fit.motor_gain.map((g) => fmt(g, 3)).join(" / ")}`;
}

function perHour(window) {
  return window.stuck_per_hour === null
    ? "no time"
    : `${fmt(window.stuck_per_hour, 1)} (${window.stuck_events} in ${fmt(window.robot_hours, 2)} robot-h)`;
}

function renderRobots(snapshot) {
  const empty = $("#robots-empty");
  const container = $("#robot-cards");
  if (!snapshot.available) {
    empty.textContent = "The robot service is not running (the server was started without zenoh).";
  } else {
    empty.textContent = "No robot has connected yet.";
  }
  empty.hidden = snapshot.robots.length > 0;
  const seen = new Set();
  for (const robot of snapshot.robots) {
    seen.add(robot.id);
    let entry = state.cards.get(robot.id);
    if (!entry) {
      entry = makeCard(robot.id);
      state.cards.set(robot.id, entry);
      container.append(entry.card);
    }
    const set = (name, ...content) => $(`[data-field="${name}"]`, entry.card).replaceChildren(...content);
    entry.online = robot.online;
    $(".dot", entry.card).classList.toggle("on", robot.online);
    $(".swatch", entry.card).style.background = robotColour(robot.id);
    if (document.activeElement !== entry.policy && !entry.policy.disabled) {
      entry.policy.value = robot.replacement_source === "robot" ? robot.replacement : "";
    }
    entry.policy.options[0].textContent = robot.replacement_source === "robot"
      ? "the colony's" : `the colony's (${robot.replacement})`;
    set("state", el("span", { class: `status ${robot.state}`, text: robot.state }));
    set("controller", el("code", { text: short(robot.controller_sha256) }));
    set("origin", robot.controller_run === null
      ? "–"
      : `run ${robot.controller_run}, rank ${robot.controller_rank ?? "?"}, ` +
        `generation ${robot.controller_generation ?? "?"}`);
    set("whiskers", whiskerBits(robot.whiskers));
    set("steps", String(robot.steps));
    set("stuck", String(robot.stuck_events));
    const f = robot.field;
    set("field", f === null
      ? "not run yet"
      : `${fmt(f.robot_hours, 3)} robot-h, ${f.stuck_events} stuck` +
        (f.stuck_per_hour === null ? "" : ` (${fmt(f.stuck_per_hour, 1)}/h)`));
    set("physics", physics(robot.calibration));
    set("calibrated", robot.calibration === null
      ? "–"
      : `${perHour(robot.before_calibration)} before calibration, ` +
        `${perHour(robot.since_calibration)} since`);
    set("seen", ago(robot.last_seen === null ? null : Date.parse(robot.last_seen) / 1000));
  }
  for (const [id, entry] of state.cards) {
    if (!seen.has(id)) {
      entry.card.remove();
      state.cards.delete(id);
      state.chosen.delete(id);
    }
  }
  fillRunChoices($("#group-run"));
  if (state.archive) fillArchiveRobots();
}

// ---- workers -------------------------------------------------------------------------------

function renderWorkers(workers) {
  $("#workers-empty").hidden = workers.length > 0;
  $("#workers-table").hidden = workers.length === 0;
  $("#workers-table tbody").replaceChildren(
    ...workers.map((w) =>
      el(
        "tr",
        { "data-worker": w.name },
        el("td", { text: w.name }),
        el("td", { text: w.host }),
        el("td", {}, el("span", { class: `status ${w.state}`, text: w.state })),
        el("td", { text: w.evaluations }),
        el("td", { text: w.robot_steps_per_s === null ? "–" : Math.round(w.robot_steps_per_s).toLocaleString() }),
        el("td", { text: ago(Date.parse(w.last_seen) / 1000) }),
      ),
    ),
  );
}

// ---- start ---------------------------------------------------------------------------------

async function startRun(event) {
  event.preventDefault();
  const form = event.target;
  const message = $("#new-run-message");
  const body = {
    population: Number(form.population.value),
    generations: Number(form.generations.value),
    seed: Number(form.seed.value),
    network: form.network.value,
  };
  try {
    const run = await api("POST", "/api/runs", body);
    message.textContent = `run ${run.id} queued`;
    onRun(run);
    selectRun(run.id);
  } catch (err) {
    message.textContent = err.message;
  }
}

function main() {
  makeChart();
  for (const button of document.querySelectorAll("#run-body .controls button")) {
    button.addEventListener("click", () => steer(button.dataset.action));
  }
  $("#new-run").addEventListener("submit", startRun);
  $("#overlay-button").addEventListener("click", showOverlay);
  $("#overlay-close").addEventListener("click", () => {
    $("#overlay-panel").hidden = true;
  });
  $("#study-cancel").addEventListener("click", cancelStudy);
  for (const img of [$("#network-img"), $("#paths-img")]) {
    img.addEventListener("click", () => zoom(img));
  }
  $("#zoom").addEventListener("click", () => $("#zoom").close());
  $("#archive-map").addEventListener("click", onArchiveClick);
  $("#archive-push").addEventListener("click", pushElite);
  $("#group-push").addEventListener("click", groupPush);
  $("#robot-panel-close").addEventListener("click", closeRobot);
  setInterval(loadRobot, ROBOT_POLL_MS);
  window.addEventListener("hashchange", showTab);
  window.addEventListener("resize", resizeChart);
  showTab();
  const wanted = Number(new URLSearchParams(location.search).get("run"));
  if (Number.isInteger(wanted) && wanted > 0) state.selected = wanted;
  renderRunDetail();
  loadStudies(); // the runs table names each run's study
  const field = $("#token");
  field.value = token();
  field.addEventListener("change", () => {
    localStorage.setItem(TOKEN_KEY, field.value.trim());
    field.classList.remove("needed");
    connect();
    loadStudies();
  });
  connect();
}

main();
