// The dashboard: runs and exposures, kept live by the event stream (/api/v1/events).
"use strict";

const API = "/api/v1";
const $ = id => document.getElementById(id);
const view = {
  run: null, exposure: null, table: null, particle: 0, slices: 0,
  yaw: 0.6, pitch: 0.35, dragging: null, topPoints: [], curves: null,
};

async function getJSON(url) {
  const r = await fetch(url, { headers: { Accept: "application/json" } });
  if (!r.ok) throw new Error(`${url}: ${r.status}`);
  return r.json();
}

function status(text) { $("status").textContent = text; }

// -- lists -------------------------------------------------------------------------------

async function loadRuns() {
  const runs = await getJSON(`${API}/runs`);
  $("current-run").textContent = runs.current;
  if (!view.run) view.run = runs.items.length ? runs.items[0].run : runs.current;
  const ul = $("runs");
  ul.replaceChildren(...runs.items.map(r => {
    const li = document.createElement("li");
    li.dataset.run = r.run;
    li.className = r.run === view.run ? "sel" : "";
    li.innerHTML = `<span>${r.run}</span><span class="small">${r.done}/${r.exposures}${r.failed ? ` · ${r.failed} failed` : ""}</span>`;
    li.onclick = () => { view.run = r.run; view.exposure = null; loadRuns(); loadExposures(true); };
    return li;
  }));
}

async function loadExposures(pickNewest) {
  if (!view.run) return;
  let data;
  try { data = await getJSON(`${API}/runs/${encodeURIComponent(view.run)}/exposures`); }
  catch (e) { $("exposures").replaceChildren(); return; }
  const items = data.items.slice().reverse();
  $("exposures").replaceChildren(...items.map(e => {
    const li = document.createElement("li");
    li.dataset.exposure = e.id;
    li.className = e.id === view.exposure ? "sel" : "";
    const state = e.state || "queued";
    const detail = state === "done" ? `${e.particles} particles`
      : state === "running" ? `${Math.round((e.progress || 0) * 100)} %` : state;
    li.innerHTML = `<span>frame ${e.frame}</span><span class="state-${state}" title="${e.error || ""}">${detail}</span>`;
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
    $("queue").textContent = `${q.total} queued · ${r.total} running`;
  } catch (e) { /* shown next time */ }
}

// -- one exposure ------------------------------------------------------------------------

async function selectExposure(id) {
  view.exposure = id;
  document.querySelectorAll("#exposures li").forEach(li => li.classList.toggle("sel", li.dataset.exposure === id));
  const [table, info] = await Promise.all([getJSON(`${API}/exposures/${id}/particles`), getJSON(`${API}/exposures/${id}`)]);
  view.table = table;
  view.curves = null;
  try { view.curves = await getJSON(`${API}/exposures/${id}/curves`); } catch (e) { view.curves = null; }
  const n = table.count;
  view.particle = Math.min(view.particle, Math.max(0, n - 1));
  $("particle").replaceChildren(...Array.from({ length: n }, (_, i) => new Option(String(i), String(i))));
  $("particle").value = String(view.particle);
  view.slices = info.slices || 0;
  $("slice").max = String(Math.max(0, view.slices - 1));
  if (+$("slice").value >= view.slices) $("slice").value = String(Math.floor(view.slices / 2));
  status(`run ${table.run} · frame ${table.frame} · ${n} particles · exposure ${id.slice(0, 12)}`);
  drawAll();
  drawSlice();
}

function drawAll() {
  const t = view.table;
  if (!t || !t.count) {
    ["scatter", "top", "curve"].forEach(c => Plot.message($(c), t ? "no particles in this exposure" : "waiting for a result"));
    return;
  }
  const c = t.columns;
  const finiteXYZ = c.X.some(Number.isFinite);
  // Without a depth model X, Y, Z are NaN: fall back to pixels and alpha.
  const [xs, ys, zs, unit] = finiteXYZ ? [c.X, c.Y, c.Z, "mm"] : [c.x, c.y, c.alpha, "px / alpha"];
  Plot.scatter3d($("scatter"), xs, ys, zs, { yaw: view.yaw, pitch: view.pitch, selected: view.particle });
  view.topPoints = Plot.scatter2d($("top"), xs, ys, zs, {
    selected: view.particle, xlabel: `X (${unit})`, ylabel: `Y (${unit})`,
    xfmt: v => v.toFixed(1), yfmt: v => v.toFixed(1),
  });
  drawCurve();
}

function drawCurve() {
  const t = view.table, i = view.particle;
  if (!t || !t.count) return;
  const c = t.columns;
  $("particle-info").textContent =
    `x ${c.x[i].toFixed(1)} px, y ${c.y[i].toFixed(1)} px, α ${c.alpha[i].toFixed(5)}` +
    (Number.isFinite(c.Z[i]) ? ` → X ${c.X[i].toFixed(3)}, Y ${c.Y[i].toFixed(3)}, Z ${c.Z[i].toFixed(3)} mm` : "");
  if (!view.curves) { Plot.message($("curve"), "no curves kept for this exposure"); return; }
  Plot.curve($("curve"), view.curves.alpha, view.curves.brightness[i].map(v => v === null ? NaN : v), {
    mark: c.alpha[i], xlabel: "α", ylabel: "B", xfmt: v => v.toFixed(3), yfmt: v => v.toExponential(0),
  });
}

async function drawSlice() {
  const canvas = $("slice-view"), k = +$("slice").value;
  if (!view.exposure || !view.slices) { Plot.message(canvas, "no slices kept"); $("slice-alpha").textContent = ""; return; }
  const r = await fetch(`${API}/exposures/${view.exposure}/slices/${k}`);
  if (!r.ok) { Plot.message(canvas, "slice not available"); return; }
  const alpha = +r.headers.get("X-Alpha"), binning = +(r.headers.get("X-Binning") || 1);
  $("slice-alpha").textContent = `α = ${alpha.toFixed(5)} (${k + 1} of ${view.slices})`;
  const bitmap = await createImageBitmap(await r.blob());
  const ctx = canvas.getContext("2d");
  ctx.imageSmoothingEnabled = false;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const s = Math.min(canvas.width / bitmap.width, canvas.height / bitmap.height);
  ctx.drawImage(bitmap, 0, 0, bitmap.width * s, bitmap.height * s);
  drawSliceMarkers(ctx, alpha, binning, s);
}

// Rings on the particles: bright where this slice is their focus, faint elsewhere.
function drawSliceMarkers(ctx, alpha, binning, scale) {
  const t = view.table;
  if (!t || !t.count || !view.curves) return;
  const a = view.curves.alpha;
  const spacing = a.length > 1 ? (a[a.length - 1] - a[0]) / (a.length - 1) * Math.ceil(a.length / view.slices) : 1;
  const c = t.columns;
  for (let i = 0; i < t.count; i++) {
    // x, y are output-image pixels (integers at pixel centres); a slice pixel spans `binning`.
    const X = ((c.x[i] - (binning - 1) / 2) / binning + 0.5) * scale;
    const Y = ((c.y[i] - (binning - 1) / 2) / binning + 0.5) * scale;
    const inFocus = Math.abs(c.alpha[i] - alpha) <= spacing / 2;
    ctx.beginPath(); ctx.arc(X, Y, inFocus ? 7 : 5, 0, 2 * Math.PI);
    ctx.strokeStyle = i === view.particle ? "#ffffff" : inFocus ? "#ffd54f" : "rgba(79,195,247,0.35)";
    ctx.lineWidth = inFocus || i === view.particle ? 2 : 1;
    ctx.stroke();
  }
}

// -- interaction -------------------------------------------------------------------------

$("scatter").addEventListener("pointerdown", e => { view.dragging = [e.clientX, e.clientY]; });
window.addEventListener("pointerup", () => { view.dragging = null; });
window.addEventListener("pointermove", e => {
  if (!view.dragging) return;
  view.yaw += (e.clientX - view.dragging[0]) * 0.01;
  view.pitch = Math.max(-1.5, Math.min(1.5, view.pitch + (e.clientY - view.dragging[1]) * 0.01));
  view.dragging = [e.clientX, e.clientY];
  drawAll();
});
$("top").addEventListener("click", e => {
  const rect = e.target.getBoundingClientRect();
  const x = (e.clientX - rect.left) * e.target.width / rect.width, y = (e.clientY - rect.top) * e.target.height / rect.height;
  let best = null, dist = 12 * 12;
  for (const [px, py, i] of view.topPoints) {
    const d = (px - x) ** 2 + (py - y) ** 2;
    if (d < dist) { dist = d; best = i; }
  }
  if (best !== null) { view.particle = best; $("particle").value = String(best); drawAll(); drawSlice(); }
});
$("particle").addEventListener("change", e => { view.particle = +e.target.value; drawAll(); drawSlice(); });
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
    try { await loadRuns(); await loadExposures(pick); await loadHeader(); } catch (e) { status(String(e)); }
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
  source.addEventListener("run", () => refreshSoon(false));
  source.onerror = () => { $("stream").textContent = "reconnecting"; $("stream").className = "pill off"; };
}

(async () => {
  ["scatter", "top", "curve", "slice-view"].forEach(c => Plot.message($(c), "waiting for a result"));
  try { await loadRuns(); await loadExposures(true); await loadHeader(); } catch (e) { status(String(e)); }
  connect();
  // Battery and queue depth change without events; a slow poll keeps them fresh.
  setInterval(loadHeader, 10000);
})();
