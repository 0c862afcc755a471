// The dashboard: runs and exposures, kept live by the event stream (/api/v1/events); plots by
// plotly.js, served by the service itself (/static/vendor/plotly.min.js), so it works offline.
"use strict";

const API = "/api/v1";
const $ = id => document.getElementById(id);
const view = { run: null, exposure: null, table: null, info: null, curves: null, particle: 0, slice: 0,
               trails: null, summary: null };
// Trails: each particle's positions over this many shots up to the one shown.
const TRAIL_SHOTS = 8;
// Camera frame (docs/camera-model.md): X right, Y down as in the upright image, Z from the lens.
// Every panel shows Y down, as the slice images do.
const DARK = {
  paper_bgcolor: "#0b0f13", plot_bgcolor: "#0b0f13", font: { color: "#c5d0da", size: 11 },
  margin: { l: 58, r: 12, t: 8, b: 42 }, uirevision: "keep",
};
const AXIS = { gridcolor: "#26313c", zerolinecolor: "#3a4652", linecolor: "#3a4652" };
const CONFIG = { displaylogo: false, responsive: true, modeBarButtonsToRemove: ["toImage", "select2d", "lasso2d"] };
const COLOURS = "Viridis";

async function getJSON(url) {
  const r = await fetch(url, { headers: { Accept: "application/json" } });
  if (!r.ok) throw new Error(`${url}: ${r.status}`);
  return r.json();
}

function status(text) { $("status").textContent = text; }

function message(id, text) {
  Plotly.purge($(id));
  $(id).clicks = false;
  $(id).innerHTML = `<div class="msg">${text}</div>`;
}

// Draw (or redraw in place, keeping the user's zoom and turn) a plot; `onClick` gets the
// particle index of a clicked point.
function plot(id, data, layout, onClick) {
  const el = $(id);
  if (!el.data) el.innerHTML = "";  // a message was shown there
  // The panel's flex layout sets the size; plotly.js would otherwise keep its default 450 px.
  Plotly.react(el, data, { ...layout, width: el.clientWidth, height: el.clientHeight }, CONFIG);
  if (onClick && !el.clicks) {
    el.on("plotly_click", ev => {
      const p = ev.points.find(q => q.customdata !== undefined);
      if (p) onClick(p.customdata);
    });
    el.clicks = true;
  }
}

// -- lists -------------------------------------------------------------------------------

async function loadRuns() {
  const runs = await getJSON(`${API}/runs`);
  $("current-run").textContent = runs.current;
  if (!view.run) view.run = runs.items.length ? runs.items[0].run : runs.current;
  // The run shown below may not be the one new shots go to: say so.
  $("viewing-run").textContent = view.run || "";
  $("viewing").hidden = !view.run || view.run === runs.current;
  $("runs").replaceChildren(...runs.items.map(r => {
    const li = document.createElement("li");
    li.dataset.run = r.run;
    li.className = r.run === view.run ? "sel" : "";
    li.innerHTML = `<span>${r.run}</span><span class="small">${r.done}/${r.exposures}${r.failed ? ` · ${r.failed} failed` : ""}</span>`;
    li.onclick = () => { view.run = r.run; view.exposure = null; loadRuns(); loadExposures(true); loadSummary(); };
    return li;
  }));
}

async function loadExposures(pickNewest) {
  if (!view.run) return;
  let data;
  // Newest first, one page: a long run lists its latest 200 frames.
  try { data = await getJSON(`${API}/runs/${encodeURIComponent(view.run)}/exposures?order=desc&limit=200`); }
  catch (e) { $("exposures").replaceChildren(); return; }
  const items = data.items;
  $("exposures").replaceChildren(...items.map(e => {
    const li = document.createElement("li");
    li.dataset.exposure = e.id;
    li.className = e.id === view.exposure ? "sel" : "";
    const state = e.state || "queued";
    const detail = state === "done" ? `${e.particles} particles`
      : state === "running" ? `${Math.round((e.progress || 0) * 100)} %` : state;
    li.innerHTML = `<span>frame ${e.frame}</span><span class="state-${state}"></span>`;
    li.lastChild.textContent = detail;
    li.lastChild.title = e.error || "";
    li.onclick = () => { if (state === "done") { $("follow").checked = false; selectExposure(e.id); } };
    return li;
  }));
  if ((pickNewest || !view.exposure) && $("follow").checked) {
    const newest = items.find(e => e.state === "done");
    if (newest && newest.id !== view.exposure) selectExposure(newest.id);
  }
}

async function loadHeader() {
  try {
    const cam = await getJSON(`${API}/camera`);
    $("camera").textContent = cam.configured
      ? `${cam.serial || "?"} · ${cam.state}${cam.battery != null ? ` · ${Math.round(cam.battery)} %` : ""}` : "none";
  } catch (e) { $("camera").textContent = "?"; }
  try {
    const [q, r] = await Promise.all([getJSON(`${API}/jobs?state=queued&limit=1`), getJSON(`${API}/jobs?state=running&limit=1`)]);
    const stage = r.items.length && r.items[0].stage ? ` (${r.items[0].stage})` : "";
    $("queue").textContent = `${q.total} queued · ${r.total} running${stage}`;
  } catch (e) { /* shown next time */ }
  try {
    const ready = await fetch("/readyz").then(x => x.json());
    $("workers").textContent = ready.workers === "warm"
      ? (ready.disk && !ready.disk.ok ? "warm · data disk full" : "warm")
      : "warming up: loading the compiled analysis kernels";
  } catch (e) { $("workers").textContent = "?"; }
}

// -- one exposure ------------------------------------------------------------------------

async function selectExposure(id) {
  view.exposure = id;
  document.querySelectorAll("#exposures li").forEach(li => li.classList.toggle("sel", li.dataset.exposure === id));
  const [table, info] = await Promise.all([getJSON(`${API}/exposures/${id}/particles`), getJSON(`${API}/exposures/${id}`)]);
  let curves = null;
  try { curves = await getJSON(`${API}/exposures/${id}/curves`); } catch (e) { curves = null; }
  Object.assign(view, { table, info, curves });
  await loadTrails();
  const n = table.count;
  view.particle = Math.min(view.particle, Math.max(0, n - 1));
  $("particle").replaceChildren(...Array.from({ length: n }, (_, i) => new Option(String(i), String(i))));
  $("particle").value = String(view.particle);
  $("slice").max = String(Math.max(0, info.slices - 1));
  status(`run ${table.run} · frame ${table.frame} · ${n} particles · exposure ${id.slice(0, 12)}`
    + (info.warnings.length ? ` · ${info.warnings.join("; ")}` : ""));
  drawAll();
  pickParticle(view.particle, { jump: true });
}

function columns() {
  const c = view.table.columns;
  // Without a depth model X, Y, Z are null: fall back to pixels and alpha.
  return c.X.some(v => v !== null) ? { x: c.X, y: c.Y, z: c.Z, unit: "mm", zname: "Z" }
    : { x: c.x, y: c.y, z: c.alpha, unit: "px", zname: "α" };
}

// Whether a particle's own pixels leave its depth open: its fitted alpha spreads over half a
// slice step or more (light in one micro-lens looks the same over a range of depths).
function depthOpen(i) {
  const s = view.table.columns.alpha_std[i], a = view.curves ? view.curves.alpha : null;
  const step = a && a.length > 1 ? (a[a.length - 1] - a[0]) / (a.length - 1) : Infinity;
  return s !== null && s >= 0.5 * step;
}

function drawAll() {
  const t = view.table;
  if (!t || !t.count) {
    ["scatter", "top", "curve"].forEach(id => message(id, t ? "no particles in this exposure" : "waiting for a result"));
    return;
  }
  const { x, y, z, unit, zname } = columns();
  const ids = x.map((_, i) => i);
  const open = ids.map(depthOpen);
  const lines = unit === "mm" ? trailLines() : { x: [], y: [], z: [], ids: {} };
  const trajectory = ids.map(i => lines.ids[i] === undefined ? "" : `<br>trajectory ${lines.ids[i]}`);
  const hover = `particle %{customdata}<br>X %{x:.3f} ${unit}<br>Y %{y:.3f} ${unit}<br>${zname} %{marker.color:.3f} ${unit}<extra></extra>`;
  const colourbar = { title: { text: `${zname} (${unit})`, side: "right" }, thickness: 10, len: 0.9, outlinewidth: 0 };
  plot("scatter", [{
    type: "scatter3d", mode: "markers", x, y, z, customdata: ids,
    marker: { size: 3.5, color: z, colorscale: COLOURS, colorbar: colourbar, opacity: 0.95 },
    hovertemplate: hover.replace("%{marker.color:.3f}", "%{z:.3f}"),
  }, selectedTrace3d(x, y, z), trailTrace(lines, true)], {
    ...DARK, margin: { l: 0, r: 0, t: 0, b: 0 },
    scene: {
      aspectmode: "data", dragmode: "turntable",
      xaxis: { ...AXIS, title: { text: `X (${unit})` }, nticks: 5, backgroundcolor: "#0b0f13", showbackground: true },
      yaxis: { ...AXIS, title: { text: `Y (${unit})` }, nticks: 5, autorange: "reversed", backgroundcolor: "#0b0f13", showbackground: true },
      zaxis: { ...AXIS, title: { text: `${zname} (${unit})` }, nticks: 5, backgroundcolor: "#0b0f13", showbackground: true },
      // Seen from behind the camera and a little above and to the right: X right, Y down, Z away.
      camera: { up: { x: 0, y: -1, z: 0 }, eye: { x: 1.5, y: -0.9, z: -1.1 }, projection: { type: "orthographic" } },
    },
  }, i => pickParticle(i, { jump: true }));
  plot("top", [{
    type: "scatter", mode: "markers", x, y, customdata: ids,
    marker: { size: 8, color: z, colorscale: COLOURS, colorbar: colourbar,
              symbol: open.map(o => o ? "circle-open" : "circle"), line: { width: 1.5 } },
    text: z.map((v, i) => `${zname} ${v === null ? "–" : v.toFixed(3)} ${unit}${open[i] ? "<br>depth left open by its pixels" : ""}${trajectory[i]}`),
    hovertemplate: `particle %{customdata}<br>X %{x:.3f} ${unit}<br>Y %{y:.3f} ${unit}<br>%{text}<extra></extra>`,
  }, selectedTrace2d(x, y), trailTrace(lines, false)], {
    ...DARK, showlegend: false, hovermode: "closest",
    xaxis: { ...AXIS, title: { text: `X (${unit}) →` }, constrain: "domain" },
    yaxis: { ...AXIS, title: { text: `Y (${unit}), down ↓` }, autorange: "reversed", scaleanchor: "x", scaleratio: 1 },
  }, i => pickParticle(i, { jump: true }));
}

// -- trajectories ----------------------------------------------------------------------------

async function loadTrails() {
  const t = view.table;
  view.trails = null;
  if (!t || t.frame === undefined || t.frame === null) return;
  const first = Math.max(0, t.frame - TRAIL_SHOTS);
  try {
    view.trails = await getJSON(`${API}/runs/${encodeURIComponent(t.run)}/trajectories?frame_min=${first}&frame_max=${t.frame}`);
  } catch (e) { view.trails = null; }  // 409 until the run's first shot is linked
}

// One line per trajectory (positions in time order), separated by gaps, for the 3D and top views.
function trailLines() {
  const tr = view.trails;
  const out = { x: [], y: [], z: [], ids: {} };
  if (!tr || !tr.count) return out;
  const c = tr.columns, rows = c.frame.map((_, i) => i);
  rows.sort((a, b) => (c.particle[a] - c.particle[b]) || (c.frame[a] - c.frame[b]));
  rows.forEach((i, k) => {
    if (k && c.particle[rows[k - 1]] !== c.particle[i]) { out.x.push(null); out.y.push(null); out.z.push(null); }
    out.x.push(c.X[i]); out.y.push(c.Y[i]); out.z.push(c.Z[i]);
    if (c.frame[i] === view.table.frame) out.ids[c.index[i]] = c.particle[i];
  });
  return out;
}

function trailTrace(lines, three) {
  const base = { mode: "lines", x: lines.x, y: lines.y, hoverinfo: "skip", showlegend: false, connectgaps: false,
                 line: { color: "rgba(255,255,255,0.55)", width: three ? 2.5 : 1.5 } };
  return three ? { ...base, type: "scatter3d", z: lines.z } : { ...base, type: "scatter" };
}

function selectedTrace3d(x, y, z) {
  const i = view.particle;
  return { type: "scatter3d", mode: "markers", x: [x[i]], y: [y[i]], z: [z[i]], hoverinfo: "skip", showlegend: false,
           marker: { size: 9, color: "rgba(0,0,0,0)", line: { color: "#ffffff", width: 3 } } };
}

function selectedTrace2d(x, y) {
  const i = view.particle;
  return { type: "scatter", mode: "markers", x: [x[i]], y: [y[i]], hoverinfo: "skip",
           marker: { size: 16, color: "rgba(0,0,0,0)", line: { color: "#ffffff", width: 2 } } };
}

// The peak of a sampled curve: the highest sample refined by a parabola through it and its neighbours.
function curvePeak(xs, ys) {
  let k = -1;
  ys.forEach((v, j) => { if (v !== null && (k < 0 || v > ys[k])) k = j; });
  if (k <= 0 || k >= ys.length - 1 || ys[k - 1] === null || ys[k + 1] === null) return k < 0 ? NaN : xs[k];
  const d = ys[k - 1] - 2 * ys[k] + ys[k + 1];
  const shift = d < 0 ? 0.5 * (ys[k - 1] - ys[k + 1]) / d : 0;
  return xs[k] + shift * (xs[k + 1] - xs[k]);
}

function drawCurve() {
  const t = view.table, i = view.particle;
  if (!t || !t.count) return;
  const c = t.columns, alpha = c.alpha[i], spread = c.alpha_std[i];
  if (!view.curves) { message("curve", "no curves kept for this exposure"); return; }
  const xs = view.curves.alpha, ys = view.curves.brightness[i];
  const peak = curvePeak(xs, ys), step = (xs[xs.length - 1] - xs[0]) / Math.max(1, xs.length - 1);
  const open = depthOpen(i);
  const shapes = [];
  const top = Math.max(...ys.filter(v => v !== null), 0) * 1.05;
  if (spread !== null && Number.isFinite(spread)) {
    shapes.push({ type: "rect", xref: "x", yref: "paper", x0: alpha - spread, x1: alpha + spread, y0: 0, y1: 1,
                  fillcolor: open ? "rgba(255,183,77,0.18)" : "rgba(255,213,79,0.10)", line: { width: 0 } });
  }
  plot("curve", [
    { type: "scatter", mode: "lines+markers", x: xs, y: ys, name: "B(α)", line: { color: "#4fc3f7", width: 2 },
      marker: { size: 4 }, hovertemplate: "α %{x:.5f}<br>B %{y:.4s} DN²<extra></extra>" },
    { type: "scatter", mode: "lines", x: [alpha, alpha], y: [0, top], name: `fitted α ${alpha.toFixed(5)} (the table's)`,
      line: { color: "#ffd54f", width: 2 }, hoverinfo: "skip" },
    { type: "scatter", mode: "lines", x: [peak, peak], y: [0, top], name: `curve peak ${Number.isFinite(peak) ? peak.toFixed(5) : "–"}`,
      line: { color: "#80deea", width: 1.5, dash: "dash" }, hoverinfo: "skip" },
  ], {
    ...DARK, margin: { l: 62, r: 12, t: 8, b: 40 }, showlegend: true,
    legend: { x: 0.01, y: 0.99, xanchor: "left", yanchor: "top", bgcolor: "rgba(11,15,19,0.75)", font: { size: 10 } },
    xaxis: { ...AXIS, title: { text: "refocus parameter α" }, tickformat: ".3f",
             range: [Math.min(xs[0], alpha) - step, Math.max(xs[xs.length - 1], alpha) + step] },
    yaxis: { ...AXIS, title: { text: "B(α), DN² per pixel" }, tickformat: "~s", range: [0, top * 1.12] },
    shapes,
  });
  const where = Number.isFinite(c.Z[i]) ? ` → X ${c.X[i].toFixed(3)}, Y ${c.Y[i].toFixed(3)}, Z ${c.Z[i].toFixed(3)} mm` : "";
  const slices = Number.isFinite(peak) ? ((alpha - peak) / step).toFixed(1) : "?";
  $("particle-info").innerHTML = `x ${c.x[i].toFixed(1)} px, y ${c.y[i].toFixed(1)} px, fitted α ${alpha.toFixed(5)}${where}. `
    + `The table holds the fitted α, from the forward-model fit to the raw pixels (how the light splits between `
    + `micro-lenses); the curve's peak (α ${Number.isFinite(peak) ? peak.toFixed(5) : "–"}) is the refocused stack's `
    + `first estimate, ${slices} slice steps away.`
    + (open ? ` <span class="flag">Depth left open by its pixels: α ± ${spread.toFixed(5)} (its light falls in one `
      + `micro-lens); where neighbours lie on one surface it takes theirs.</span>` : "")
    + (alpha < xs[0] || alpha > xs[xs.length - 1] ? ` <span class="flag">The fitted α lies outside the refocused range.</span>` : "");
}

function nearestSlice(alpha) {
  const a = view.info ? view.info.slice_alpha : [];
  let best = 0;
  a.forEach((v, k) => { if (Math.abs(v - alpha) < Math.abs(a[best] - alpha)) best = k; });
  return best;
}

function pickParticle(i, { jump } = {}) {
  if (!view.table || !view.table.count) { drawAll(); drawSlice(); return; }
  view.particle = i;
  $("particle").value = String(i);
  const { x, y, z } = columns();
  // Move the white ring (trace 1) of the 3D and top views onto the particle.
  if ($("scatter").data) Plotly.restyle($("scatter"), { x: [[x[i]]], y: [[y[i]]], z: [[z[i]]] }, [1]);
  if ($("top").data) Plotly.restyle($("top"), { x: [[x[i]]], y: [[y[i]]] }, [1]);
  drawCurve();
  if (jump && view.info && view.info.slices) $("slice").value = String(nearestSlice(view.table.columns.alpha[i]));
  drawSlice();
}

function drawSlice() {
  const info = view.info, t = view.table;
  if (!view.exposure || !info || !info.slices) { message("slice-view", "no slices kept"); $("slice-alpha").textContent = ""; return; }
  const k = +$("slice").value, alpha = info.slice_alpha[k], b = info.slice_binning;
  const step = info.slices > 1 ? (info.slice_alpha[info.slices - 1] - info.slice_alpha[0]) / (info.slices - 1) : 1;
  $("slice-alpha").textContent = `α = ${alpha.toFixed(5)} (${k + 1} of ${info.slices}) · output-image pixels, y down · `
    + `yellow: particles in focus here, white: particle ${view.particle}`;
  const c = t && t.count ? t.columns : { x: [], y: [], alpha: [] };
  const ids = c.x.map((_, i) => i);
  const focus = ids.filter(i => Math.abs(c.alpha[i] - alpha) <= step / 2);
  const others = ids.filter(i => Math.abs(c.alpha[i] - alpha) > step / 2);
  const ring = (sel, colour, size) => ({
    type: "scatter", mode: "markers", x: sel.map(i => c.x[i]), y: sel.map(i => c.y[i]), customdata: sel,
    marker: { size, color: "rgba(0,0,0,0)", line: { color: colour, width: 1.5 } },
    hovertemplate: "particle %{customdata}<br>x %{x:.1f} px, y %{y:.1f} px<extra></extra>",
  });
  const n = view.particle;
  // The PNG's pixel (i, j) covers output-image pixels [b*j, b*(j+1)) across: place it so.
  const img = new Image();
  img.onload = () => {
    const w = img.width * b, h = img.height * b;
    plot("slice-view", [ring(others, "rgba(79,195,247,0.35)", 9), ring(focus, "#ffd54f", 12),
      { ...ring(t && t.count ? [n] : [], "#ffffff", 16), marker: { size: 16, color: "rgba(0,0,0,0)", line: { color: "#fff", width: 2.5 } } }], {
      ...DARK, showlegend: false, hovermode: "closest", margin: { l: 46, r: 8, t: 6, b: 34 },
      xaxis: { ...AXIS, range: [-0.5, w - 0.5], title: { text: "x (px) →" }, constrain: "domain", showgrid: false },
      yaxis: { ...AXIS, range: [h - 0.5, -0.5], title: { text: "y (px), down ↓" }, scaleanchor: "x", showgrid: false },
      images: [{ source: img.src, xref: "x", yref: "y", x: -0.5, y: -0.5, sizex: w, sizey: h, sizing: "stretch",
                 xanchor: "left", yanchor: "top", layer: "below" }],
    }, i => pickParticle(i, { jump: false }));
  };
  img.src = `${API}/exposures/${view.exposure}/slices/${k}`;
}

// -- the run over time --------------------------------------------------------------------

async function loadSummary() {
  if (!view.run) return;
  try { view.summary = await getJSON(`${API}/runs/${encodeURIComponent(view.run)}/summary`); }
  catch (e) { view.summary = null; }
  drawTimeline();
}

function drawTimeline() {
  const s = view.summary;
  if (!s || !s.count) { message("timeline", "no linked shots in this run yet"); return; }
  const c = s.columns, t = c.t;
  const line = (y, name, colour, axis, err) => ({
    type: "scatter", mode: "lines+markers", x: t, y, name, xaxis: "x", yaxis: axis, marker: { size: 4 },
    line: { color: colour, width: 1.5 }, error_y: err ? { type: "data", array: err, visible: true, thickness: 1, width: 0 } : undefined,
    hovertemplate: `${name} %{y:.4g}<br>t %{x:.1f} s<extra></extra>`,
  });
  const data = [line(c.count, "particles", "#4fc3f7", "y"),
                line(c.T_xy_eV, "T lateral (X, Y)", "#ffd54f", "y2", c.T_xy_err_eV),
                line(c.T_eV, "T (X, Y, Z)", "#ff8a65", "y2", c.T_err_eV)];
  // Shells are found shot by shot: "shell k" is the same shell only in shots with as many shells,
  // so the occupations are drawn for the shots with the run's usual number of shells (gaps elsewhere).
  const shellColours = ["#81c784", "#ba68c8", "#4db6ac", "#f06292", "#aed581"];
  const usual = mode(c.shells || []);
  const same = (c.shells || []).map(n => n === usual);
  const only = v => v.map((x, i) => same[i] ? x : null);
  for (let k = 0; k < usual && c[`shell${k}_n`]; k++) {
    data.push(line(only(c[`shell${k}_n`]), `shell ${k + 1} (r ≈ ${median(only(c[`shell${k}_r_mm`])).toFixed(2)} mm)`,
                   shellColours[k % shellColours.length], "y3", c[`shell${k}_n_err`] && only(c[`shell${k}_n_err`])));
  }
  const shellNote = usual ? ` · ${usual} shells in ${same.filter(Boolean).length} of ${same.length} shots`
    + (same.every(Boolean) ? "" : " (occupations drawn for those)") : "";
  const noise = ["X", "Y", "Z"].map(a => c[`noise_${a}_mm`] ? median(c[`noise_${a}_mm`]) : NaN);
  $("run-info").textContent = `run ${s.run} · ${s.count} linked shots · position noise X ${fmtUm(noise[0])}, `
    + `Y ${fmtUm(noise[1])}, Z ${fmtUm(noise[2])} (taken out of the temperatures) · particle mass ${s.particle_mass_kg.toExponential(2)} kg${shellNote}`;
  plot("timeline", data, {
    // A top margin for the mode bar, which would otherwise cover the legend's first entry.
    ...DARK, margin: { l: 62, r: 12, t: 30, b: 40 }, showlegend: true, hovermode: "x unified",
    legend: { x: 1.01, xanchor: "left", y: 1, bgcolor: "rgba(11,15,19,0.75)", font: { size: 10 } },
    xaxis: { ...AXIS, title: { text: "t (s since the run's first shot)" }, anchor: "y3" },
    yaxis: { ...AXIS, domain: [0.70, 1], title: { text: "particles" }, rangemode: "tozero" },
    yaxis2: { ...AXIS, domain: [0.36, 0.64], title: { text: "T (eV)" }, tickformat: ".4~f", rangemode: "tozero" },
    yaxis3: { ...AXIS, domain: [0, 0.30], title: { text: "per shell" }, rangemode: "tozero" },
  });
}

// The most frequent finite value (0 when there is none).
function mode(values) {
  const counts = new Map();
  values.forEach(v => { if (v !== null && Number.isFinite(v)) counts.set(v, (counts.get(v) || 0) + 1); });
  let best = 0, most = 0;
  counts.forEach((n, v) => { if (n > most || (n === most && v > best)) { best = v; most = n; } });
  return best;
}

function median(values) {
  const v = values.filter(x => x !== null && Number.isFinite(x)).sort((a, b) => a - b);
  return v.length ? v[Math.floor(v.length / 2)] : NaN;
}

function fmtUm(mm) { return Number.isFinite(mm) ? `${(mm * 1000).toFixed(1)} µm` : "–"; }

// -- interaction -------------------------------------------------------------------------

$("particle").addEventListener("change", e => pickParticle(+e.target.value, { jump: true }));
// A window or panel that changes size redraws its plot to fit.
const resized = new ResizeObserver(entries => entries.forEach(({ target }) => {
  if (target.data) Plotly.relayout(target, { width: target.clientWidth, height: target.clientHeight });
}));
document.querySelectorAll(".plot").forEach(el => resized.observe(el));
$("slice").addEventListener("input", drawSlice);

// -- live updates --------------------------------------------------------------------------

// Events come in bursts (job queued, running, done, result): refresh once per burst, and
// jump to the newest result if any event of the burst asked for it.
let refreshPending = false, pickPending = false;
function refreshSoon(pickNewest) {
  pickPending = pickPending || pickNewest;
  if (refreshPending) return;
  refreshPending = true;
  setTimeout(async () => {
    const pick = pickPending;
    refreshPending = false; pickPending = false;
    try { await loadRuns(); await loadExposures(pick); await loadHeader(); await loadSummary(); } catch (e) { status(String(e)); }
  }, 150);
}

function connect() {
  const source = new EventSource(`${API}/events`);
  source.addEventListener("hello", () => { $("stream").textContent = "live"; $("stream").className = "pill on"; refreshSoon(true); });
  source.addEventListener("job", () => refreshSoon(false));
  source.addEventListener("result", ev => {
    const data = JSON.parse(ev.data);
    if (!view.run || data.run === view.run || $("follow").checked) view.run = data.run;
    refreshSoon(true);
  });
  source.addEventListener("camera", () => loadHeader());
  // A shot was linked: the run's time plots and the trails change.
  source.addEventListener("tracks", async ev => {
    const data = JSON.parse(ev.data);
    if (data.run !== view.run) return;
    await loadSummary();
    if (view.table && data.frames.includes(view.table.frame)) { await loadTrails(); drawAll(); pickParticle(view.particle); }
  });
  source.addEventListener("run", () => refreshSoon(false));
  source.onerror = () => { $("stream").textContent = "reconnecting"; $("stream").className = "pill off"; };
}

(async () => {
  ["scatter", "top", "curve", "slice-view", "timeline"].forEach(id => message(id, "waiting for a result"));
  try { await loadRuns(); await loadExposures(true); await loadHeader(); await loadSummary(); } catch (e) { status(String(e)); }
  connect();
  // Battery, queue depth and the workers' warm-up change without events; a slow poll keeps them fresh.
  setInterval(loadHeader, 3000);
})();
