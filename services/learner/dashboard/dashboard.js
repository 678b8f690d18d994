// The run dashboard: polls /status and /history and draws them with uPlot (vendored).
// No framework and no build step; window.nasaDashboard exposes what is drawn (for tests).
"use strict";

const POLL_MS = 2000;
// A learner that accepts and never answers (stopped, hung, its host cut off) would leave a fetch,
// and so the page's "running", waiting for ever: each request gives up after this long.
const ANSWER_MS = 10000;
const COLORS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#17becf"];
const charts = {};
const state = { status: null, history: null, polls: 0 };
window.nasaDashboard = { charts, state, fmt };

function fmt(v, digits = 3) {
  if (v === null || v === undefined) return "–";
  if (typeof v === "boolean") return v ? "yes" : "no";
  if (Number.isInteger(v)) return v.toLocaleString("en");
  const n = Number(v);
  // Whole units from 10^(digits-1) up: toPrecision writes 999.7 as "1.00e+3".
  if (Math.abs(n) >= 10 ** (digits - 1)) return Math.round(n).toLocaleString("en");
  return n.toPrecision(digits);
}

function bytes(v) {
  if (v === null || v === undefined) return "–";
  const units = ["B", "KiB", "MiB", "GiB", "TiB"];
  let i = 0;
  while (v >= 1024 && i < units.length - 1) { v /= 1024; i++; }
  return v.toFixed(1) + " " + units[i];
}

function chartWidth(el) { return Math.max(260, el.clientWidth || 300); }

// One uPlot chart against env steps; `series`: [{label, dash?, scale?}], `axes2`: a right-hand scale.
function makeChart(id, series, opts = {}) {
  const el = typeof id === "string" ? document.getElementById(id) : id;
  const uSeries = [{ label: "env steps" }].concat(series.map((s, i) => ({
    label: s.label, stroke: s.color || COLORS[i % COLORS.length], width: 1.5, dash: s.dash,
    scale: s.scale || "y", spanGaps: true, points: { show: s.points || false },
    value: (u, v) => s.format ? s.format(v) : fmt(v),
  })));
  const axes = [{ label: "env steps", size: 40 }, { scale: "y", size: 56, values: opts.yValues }];
  if (opts.y2) axes.push({ scale: "y2", side: 1, size: opts.y2Size || 56, grid: { show: false }, values: opts.y2Values });
  const chart = new uPlot({
    width: chartWidth(el), height: opts.height || 200, series: uSeries, axes,
    scales: { x: { time: false } }, legend: { live: true }, cursor: { drag: { x: true, y: false } },
  }, [[]].concat(series.map(() => [])), el);
  new ResizeObserver(() => chart.setSize({ width: chartWidth(el), height: opts.height || 200 })).observe(el);
  charts[typeof id === "string" ? id.replace("chart-", "") : opts.name] = chart;
  return chart;
}

function columns(points, keys) {
  return [points.map(p => p.env_steps)].concat(keys.map(k => points.map(p => (typeof k === "function" ? k(p) : p[k]) ?? null)));
}

function setupCharts() {
  makeChart("chart-eval", [
    { label: "eval return (mean)", points: true },
    { label: "untrained policy (step 0)", dash: [6, 4], color: "#888" },
  ], { height: 240 });
  makeChart("chart-rates", [{ label: "env steps/s" }, { label: "updates/s", scale: "y2" }], { y2: true });
  makeChart("chart-ratio", [{ label: "updates per env step" }, { label: "target G", dash: [6, 4], color: "#888" }]);
  makeChart("chart-lag", [{ label: "mean" }, { label: "max" }]);
  makeChart("chart-intrinsic", [{ label: "novelty mean" }, { label: "surprise mean", scale: "y2" }], { y2: true });
  makeChart("chart-replay", [
    { label: "size (transitions)" },
    { label: "memory", scale: "y2", format: bytes },
  ], { y2: true, y2Size: 76, y2Values: (u, vals) => vals.map(bytes) });
  makeChart("chart-invalid", [{ label: "learner" }, { label: "replay" }]);
}

function drawHistory(h) {
  const evals = h.evals || [];
  const start = evals.find(e => e.step === 0);
  charts.eval.setData([evals.map(e => e.step), evals.map(e => e.mean),
                       evals.map(() => (start ? start.mean : null))]);
  const p = h.points || [];
  charts.rates.setData(columns(p, ["env_steps_per_s", "updates_per_s"]));
  charts.ratio.setData(columns(p, ["updates_per_env_step", "target"]));
  charts.lag.setData(columns(p, ["lag_mean", "lag_max"]));
  charts.intrinsic.setData(columns(p, ["novelty_mean", "surprise_mean"]));
  charts.replay.setData(columns(p, ["replay_size", "replay_bytes"]));
  charts.invalid.setData(columns(p, ["invalid_messages", "replay_invalid_messages"]));
  drawLosses(p);
  drawMedia(h.media);
}

function drawLosses(points) {
  const names = [...new Set(points.flatMap(p => Object.keys(p.losses || {})))].sort();
  const box = document.getElementById("losses");
  for (const name of names) {
    const key = "loss:" + name;
    if (!charts[key]) {
      const wrap = document.createElement("div");
      wrap.innerHTML = `<h3>${name}</h3>`;
      const el = document.createElement("div");
      el.className = "chart";
      wrap.appendChild(el);
      box.appendChild(wrap);
      makeChart(el, [{ label: name }], { name: key, height: 160 });
    }
    charts[key].setData(columns(points, [p => (p.losses || {})[name]]));
  }
}

function drawMedia(media) {
  if (!media) return;
  const ae = media.autoencoder;
  if (ae) {
    const img = document.getElementById("ae-image");
    const src = "/media/" + ae.image + "?step=" + ae.step;
    if (img.getAttribute("src") !== src) img.setAttribute("src", src);
    document.getElementById("ae-caption").textContent =
      `eval step ${fmt(ae.step)}, autoencoder of policy ${fmt(ae.autoencoder_version)}`;
    document.getElementById("ae-novelty").textContent =
      // A non-finite novelty (a diverged autoencoder) comes as null: shown as "–", never a throw
      // that would leave the whole page on an error.
      "novelty: " + (ae.novelty || []).map(v => (typeof v === "number" ? v.toFixed(3) : "–")).join("  ");
  }
  const videos = media.videos || [];
  if (videos.length) {
    document.getElementById("videos").innerHTML = videos.slice().reverse().map(v =>
      `<li><a href="/media/${v.file}">eval step ${fmt(v.step)}</a> <small>${v.frames} frames, return ${fmt(v.return)}</small></li>`).join("");
  }
}

function drawStatus(s) {
  document.getElementById("title").textContent = `${s.algo} on ${s.task}`;
  document.getElementById("summary").textContent =
    `run ${s.run_id} · ${s.device} · env steps ${fmt(s.env_steps)} / ${fmt(s.steps_budget)}` +
    // A step is action_repeat frames; an older run's status has no such field.
    (s.action_repeat ? ` (action repeat ${s.action_repeat}: ${fmt(s.env_steps * s.action_repeat)} frames)` : "") +
    ` · updates ${fmt(s.updates)} · ${fmt(s.env_steps_per_s)} steps/s · ${fmt(s.updates_per_s)} updates/s`;
  const e = s.eval || {};
  const latest = document.getElementById("eval-latest");
  latest.textContent = e.step === null || e.step === undefined ? "no evaluation yet" :
    `latest: ${fmt(e.mean)} ± ${fmt(e.std)} at step ${fmt(e.step)}`;
  latest.dataset.step = e.step ?? "";
  latest.dataset.mean = e.mean ?? "";
  const body = document.querySelector("#actors tbody");
  body.innerHTML = "";
  for (const a of s.actors || []) {
    const tr = document.createElement("tr");
    tr.dataset.actor = a.id;
    const cells = [a.id, a.alive ? "yes" : "no", a.incarnation, a.env_steps, a.episodes, a.steps_per_s,
                   a.policy_version, s.policy_version - a.policy_version, a.last_seen_s + " s", a.fault ?? "–"];
    const keys = ["id", "alive", "incarnation", "env_steps", "episodes", "steps_per_s", "policy_version",
                  "lag", "last_seen_s", "fault"];
    cells.forEach((v, i) => {
      const td = document.createElement("td");
      td.textContent = typeof v === "number" ? fmt(v) : v;
      td.dataset.key = keys[i];
      td.dataset.value = String(i === 1 ? a.alive : (typeof v === "number" ? v : (a[keys[i]] ?? "")));
      if (i === 1 && !a.alive) td.className = "dead";
      if (i === 9 && a.fault && a.fault !== "ok") td.className = "dead";  // a bridge's fault or e-stop
      tr.appendChild(td);
    });
    body.appendChild(tr);
  }
}

async function get(path) {
  try {
    return await fetch(path, { cache: "no-store", signal: AbortSignal.timeout(ANSWER_MS) });
  } catch (err) {
    throw err.name === "TimeoutError" ? new Error(`${path}: no answer in ${ANSWER_MS / 1000} s`) : err;
  }
}

async function getJSON(path) {
  const r = await get(path);
  if (!r.ok) throw new Error(`${path}: HTTP ${r.status}`);
  return r.json();
}

async function poll() {
  const stateEl = document.getElementById("state");
  try {
    const [s, h] = await Promise.all([getJSON("/status"), getJSON("/history")]);
    const health = await get("/healthz");
    state.status = s;
    state.history = h;
    drawStatus(s);
    drawHistory(h);
    state.polls++;
    // 200 is "ok" or "degraded: <why>" (writes the disk refuses while training goes on).
    const said = (await health.text()).trim();
    const degraded = health.ok && said.startsWith("degraded");
    stateEl.textContent = health.ok && !degraded ? "running" : said;
    stateEl.className = "state" + (degraded ? " degraded" : health.ok ? "" : " stopped");
  } catch (err) {
    stateEl.textContent = "no answer: " + err.message;
    stateEl.className = "state error";
  }
  setTimeout(poll, POLL_MS);
}

setupCharts();
poll();
