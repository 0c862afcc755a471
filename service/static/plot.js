// Small canvas plots for the dashboard: no library, works offline.
"use strict";

const Plot = (() => {
  // A perceptually ordered colour ramp (dark blue -> teal -> yellow), t in [0, 1].
  const RAMP = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];
  function colour(t) {
    if (!Number.isFinite(t)) return "rgb(128,128,128)";
    t = Math.min(1, Math.max(0, t)) * (RAMP.length - 1);
    const i = Math.min(RAMP.length - 2, Math.floor(t)), f = t - i;
    const c = RAMP[i].map((v, k) => Math.round(v + f * (RAMP[i + 1][k] - v)));
    return `rgb(${c[0]},${c[1]},${c[2]})`;
  }

  function finiteRange(values) {
    let lo = Infinity, hi = -Infinity;
    for (const v of values) if (Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    if (lo === Infinity) return [0, 1];
    if (hi - lo < 1e-12) { lo -= 0.5; hi += 0.5; }
    return [lo, hi];
  }

  function niceTicks(lo, hi, count) {
    const span = hi - lo, raw = span / Math.max(1, count);
    const mag = Math.pow(10, Math.floor(Math.log10(raw)));
    const step = [1, 2, 5, 10].map(m => m * mag).find(s => span / s <= count) || raw;
    const ticks = [];
    for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) ticks.push(+v.toPrecision(12));
    return ticks;
  }

  function clear(ctx) {
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, ctx.canvas.width, ctx.canvas.height);
  }

  function message(canvas, text) {
    const ctx = canvas.getContext("2d");
    clear(ctx);
    ctx.fillStyle = "#8a98a6";
    ctx.font = "14px system-ui, sans-serif";
    ctx.textAlign = "center";
    ctx.fillText(text, canvas.width / 2, canvas.height / 2);
  }

  // Axes box with ticks; returns a mapping from data to pixels.
  function axes(ctx, xr, yr, opts) {
    const W = ctx.canvas.width, H = ctx.canvas.height, m = { l: 52, r: 12, t: 10, b: 36 };
    const px = x => m.l + (x - xr[0]) / (xr[1] - xr[0]) * (W - m.l - m.r);
    const py = y => H - m.b - (y - yr[0]) / (yr[1] - yr[0]) * (H - m.t - m.b);
    ctx.strokeStyle = "#2a3440"; ctx.fillStyle = "#8a98a6"; ctx.lineWidth = 1;
    ctx.font = "11px system-ui, sans-serif";
    ctx.textAlign = "center";
    for (const t of niceTicks(xr[0], xr[1], 6)) {
      ctx.beginPath(); ctx.moveTo(px(t), m.t); ctx.lineTo(px(t), H - m.b); ctx.stroke();
      ctx.fillText(opts.xfmt ? opts.xfmt(t) : String(t), px(t), H - m.b + 14);
    }
    ctx.textAlign = "right";
    for (const t of niceTicks(yr[0], yr[1], 5)) {
      ctx.beginPath(); ctx.moveTo(m.l, py(t)); ctx.lineTo(W - m.r, py(t)); ctx.stroke();
      ctx.fillText(opts.yfmt ? opts.yfmt(t) : String(t), m.l - 4, py(t) + 4);
    }
    ctx.textAlign = "center";
    ctx.fillText(opts.xlabel || "", (m.l + W - m.r) / 2, H - 4);
    ctx.save(); ctx.translate(12, (m.t + H - m.b) / 2); ctx.rotate(-Math.PI / 2);
    ctx.fillText(opts.ylabel || "", 0, 0); ctx.restore();
    return { px, py };
  }

  // Top view: x, y in mm with equal scales; returns screen positions for picking.
  function scatter2d(canvas, xs, ys, cs, opts) {
    const ctx = canvas.getContext("2d");
    clear(ctx);
    let xr = finiteRange(xs), yr = finiteRange(ys);
    const half = Math.max(xr[1] - xr[0], yr[1] - yr[0]) / 2 * 1.1;
    const cx = (xr[0] + xr[1]) / 2, cy = (yr[0] + yr[1]) / 2;
    xr = [cx - half, cx + half]; yr = [cy - half, cy + half];
    const { px, py } = axes(ctx, xr, yr, opts);
    const cr = finiteRange(cs), points = [];
    xs.forEach((x, i) => {
      if (!Number.isFinite(x) || !Number.isFinite(ys[i])) return;
      const X = px(x), Y = py(ys[i]);
      points.push([X, Y, i]);
      ctx.beginPath(); ctx.arc(X, Y, i === opts.selected ? 6 : 4, 0, 2 * Math.PI);
      ctx.fillStyle = colour((cs[i] - cr[0]) / (cr[1] - cr[0])); ctx.fill();
      if (i === opts.selected) { ctx.strokeStyle = "#fff"; ctx.lineWidth = 2; ctx.stroke(); }
    });
    return points;
  }

  // Orthographic 3D scatter turned by yaw and pitch, with a bounding box for orientation.
  function scatter3d(canvas, xs, ys, zs, opts) {
    const ctx = canvas.getContext("2d");
    clear(ctx);
    const W = canvas.width, H = canvas.height;
    const rx = finiteRange(xs), ry = finiteRange(ys), rz = finiteRange(zs);
    const c = [(rx[0] + rx[1]) / 2, (ry[0] + ry[1]) / 2, (rz[0] + rz[1]) / 2];
    const size = Math.max(rx[1] - rx[0], ry[1] - ry[0], rz[1] - rz[0]) || 1;
    const s = 0.55 * Math.min(W, H) / size;
    const cy = Math.cos(opts.yaw), sy = Math.sin(opts.yaw), cp = Math.cos(opts.pitch), sp = Math.sin(opts.pitch);
    const project = (x, y, z) => {
      const a = x - c[0], b = y - c[1], d = z - c[2];
      const u = a * cy + d * sy, w = -a * sy + d * cy;
      const v = b * cp - w * sp, depth = b * sp + w * cp;
      return [W / 2 + s * u, H / 2 + s * v, depth];
    };
    // Bounding box edges.
    const corners = [];
    for (const x of rx) for (const y of ry) for (const z of rz) corners.push(project(x, y, z));
    ctx.strokeStyle = "#2a3440"; ctx.lineWidth = 1;
    for (let i = 0; i < 8; i++) for (let j = i + 1; j < 8; j++) {
      const diff = (i ^ j);
      if (diff === 1 || diff === 2 || diff === 4) {
        ctx.beginPath(); ctx.moveTo(corners[i][0], corners[i][1]); ctx.lineTo(corners[j][0], corners[j][1]); ctx.stroke();
      }
    }
    // Axis labels at the box's lowest corner.
    ctx.fillStyle = "#8a98a6"; ctx.font = "11px system-ui, sans-serif"; ctx.textAlign = "left";
    [["X", project(rx[1], ry[0], rz[0])], ["Y", project(rx[0], ry[1], rz[0])], ["Z", project(rx[0], ry[0], rz[1])]]
      .forEach(([name, p]) => { ctx.fillText(name, p[0] + 4, p[1]); });
    ctx.fillText(`box ${(rx[1] - rx[0]).toFixed(2)} × ${(ry[1] - ry[0]).toFixed(2)} × ${(rz[1] - rz[0]).toFixed(2)} mm`, 8, H - 8);
    // Painter's order: far points first.
    const pts = [];
    xs.forEach((x, i) => {
      if ([x, ys[i], zs[i]].every(Number.isFinite)) pts.push([...project(x, ys[i], zs[i]), i]);
    });
    pts.sort((a, b) => a[2] - b[2]);
    for (const [X, Y, , i] of pts) {
      ctx.beginPath(); ctx.arc(X, Y, i === opts.selected ? 6 : 4, 0, 2 * Math.PI);
      ctx.fillStyle = colour((zs[i] - rz[0]) / (rz[1] - rz[0])); ctx.fill();
      if (i === opts.selected) { ctx.strokeStyle = "#fff"; ctx.lineWidth = 2; ctx.stroke(); }
    }
  }

  // Line plot of one curve with markers, and a vertical line at `mark`.
  function curve(canvas, xs, ys, opts) {
    const ctx = canvas.getContext("2d");
    clear(ctx);
    const xr = finiteRange(xs), yr0 = finiteRange(ys);
    const yr = [Math.min(0, yr0[0]), yr0[1] * 1.08];
    const { px, py } = axes(ctx, xr, yr, opts);
    ctx.strokeStyle = "#4fc3f7"; ctx.lineWidth = 2; ctx.beginPath();
    let pen = false;
    xs.forEach((x, i) => {
      if (!Number.isFinite(ys[i])) { pen = false; return; }
      if (pen) ctx.lineTo(px(x), py(ys[i])); else { ctx.moveTo(px(x), py(ys[i])); pen = true; }
    });
    ctx.stroke();
    ctx.fillStyle = "#4fc3f7";
    xs.forEach((x, i) => { if (Number.isFinite(ys[i])) { ctx.beginPath(); ctx.arc(px(x), py(ys[i]), 2.5, 0, 2 * Math.PI); ctx.fill(); } });
    if (Number.isFinite(opts.mark)) {
      ctx.strokeStyle = "#ffd54f"; ctx.setLineDash([4, 4]); ctx.beginPath();
      ctx.moveTo(px(opts.mark), py(yr[0])); ctx.lineTo(px(opts.mark), py(yr[1])); ctx.stroke(); ctx.setLineDash([]);
    }
  }

  return { colour, scatter2d, scatter3d, curve, message };
})();
