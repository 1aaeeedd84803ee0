// Error against run time on a <canvas>, drawn here (no chart library, nothing fetched):
// held-out PSNR (left axis) and, where the scene has ground truth, Chamfer distance x100
// (right axis) over training seconds (the metrics endpoint's wall_time).

function niceStep(span, count) {
  const raw = span / Math.max(count, 1);
  const mag = 10 ** Math.floor(Math.log10(raw));
  const f = raw / mag;
  return (f >= 7.5 ? 10 : f >= 3.5 ? 5 : f >= 1.5 ? 2 : 1) * mag;
}

function axis(lo, hi, count) {
  if (!(hi > lo)) { const pad = Math.abs(lo) * 0.05 || 1; lo -= pad; hi += pad; }
  const step = niceStep(hi - lo, count);
  const a = Math.floor(lo / step) * step, b = Math.ceil(hi / step) * step;
  const ticks = [];
  for (let v = a; v <= b + step * 1e-6; v += step) ticks.push(Number(v.toFixed(10)));
  return { lo: a, hi: b, ticks, step };
}

function label(v, step) {
  const digits = step >= 1 ? 0 : Math.min(4, Math.ceil(-Math.log10(step)));
  return v.toFixed(digits);
}

const css = (el, name, fallback) => getComputedStyle(el).getPropertyValue(name).trim() || fallback;

/**
 * Draw rows ({wall_time, psnr, cd_x100?}) on the canvas at its CSS size and device pixel
 * ratio. Returns what was drawn: {psnr: n points, cd: n points}.
 */
export function drawChart(canvas, rows, { budgetS = null } = {}) {
  const dpr = Math.min(window.devicePixelRatio || 1, 3);
  const W = Math.max(canvas.clientWidth, 200), H = Math.max(canvas.clientHeight, 120);
  canvas.width = Math.round(W * dpr);
  canvas.height = Math.round(H * dpr);
  const ctx = canvas.getContext("2d");
  ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
  ctx.clearRect(0, 0, W, H);
  const text = css(canvas, "--text", "#e6e8ee"), muted = css(canvas, "--muted", "#8a93a6");
  const grid = css(canvas, "--line", "#262b36"), c1 = css(canvas, "--accent", "#5aa9ff");
  const c2 = css(canvas, "--warn", "#f5b14c");
  ctx.font = "12px system-ui, sans-serif";

  const ps = rows.filter((r) => Number.isFinite(r.psnr) && Number.isFinite(r.wall_time));
  const cd = rows.filter((r) => Number.isFinite(r.cd_x100) && Number.isFinite(r.wall_time));
  if (!ps.length && !cd.length) {
    ctx.fillStyle = muted;
    ctx.textAlign = "center";
    ctx.fillText("No evaluation yet: the chart fills in as the job evaluates.", W / 2, H / 2);
    return { psnr: 0, cd: 0 };
  }
  const all = ps.concat(cd);
  let tMax = Math.max(...all.map((r) => r.wall_time), budgetS || 0, 1e-3);
  const minutes = tMax > 300;
  const unit = minutes ? 60 : 1;
  const x = axis(0, tMax / unit, 6);
  const pad = { l: 52, r: cd.length ? 58 : 18, t: 26, b: 38 };
  const pw = W - pad.l - pad.r, ph = H - pad.t - pad.b;
  const X = (t) => pad.l + ((t / unit - x.lo) / (x.hi - x.lo)) * pw;

  const yP = ps.length ? axis(Math.min(...ps.map((r) => r.psnr)), Math.max(...ps.map((r) => r.psnr)), 5) : null;
  const yC = cd.length ? axis(0, Math.max(...cd.map((r) => r.cd_x100)), 5) : null;
  const Y = (ax, v) => pad.t + ph - ((v - ax.lo) / (ax.hi - ax.lo)) * ph;

  // grid and axes
  ctx.strokeStyle = grid;
  ctx.lineWidth = 1;
  ctx.fillStyle = muted;
  ctx.textAlign = "center";
  ctx.textBaseline = "top";
  for (const t of x.ticks) {
    const px = Math.round(pad.l + ((t - x.lo) / (x.hi - x.lo)) * pw) + 0.5;
    ctx.beginPath(); ctx.moveTo(px, pad.t); ctx.lineTo(px, pad.t + ph); ctx.stroke();
    ctx.fillText(label(t, x.step), px, pad.t + ph + 6);
  }
  ctx.fillText(minutes ? "training time (min)" : "training time (s)", pad.l + pw / 2, H - 16);
  const left = yP || yC;
  ctx.textAlign = "right";
  ctx.textBaseline = "middle";
  for (const v of left.ticks) {
    const py = Math.round(Y(left, v)) + 0.5;
    ctx.beginPath(); ctx.moveTo(pad.l, py); ctx.lineTo(pad.l + pw, py); ctx.stroke();
    ctx.fillText(label(v, left.step), pad.l - 6, py);
  }
  if (yP && yC) {
    ctx.textAlign = "left";
    for (const v of yC.ticks) ctx.fillText(label(v, yC.step), pad.l + pw + 6, Y(yC, v));
  }
  if (budgetS) { // the time budget's end
    const bx = Math.round(X(budgetS)) + 0.5;
    ctx.setLineDash([4, 4]);
    ctx.strokeStyle = muted;
    ctx.beginPath(); ctx.moveTo(bx, pad.t); ctx.lineTo(bx, pad.t + ph); ctx.stroke();
    ctx.setLineDash([]);
  }

  function series(points, key, ax, color, dashed) {
    ctx.strokeStyle = color;
    ctx.fillStyle = color;
    ctx.lineWidth = 2;
    ctx.setLineDash(dashed ? [6, 4] : []);
    ctx.beginPath();
    points.forEach((r, i) => {
      const px = X(r.wall_time), py = Y(ax, r[key]);
      if (i) ctx.lineTo(px, py); else ctx.moveTo(px, py);
    });
    ctx.stroke();
    ctx.setLineDash([]);
    for (const r of points) {
      ctx.beginPath(); ctx.arc(X(r.wall_time), Y(ax, r[key]), 3, 0, Math.PI * 2); ctx.fill();
    }
  }
  if (yP) series(ps, "psnr", yP, c1, false);
  if (yC) series(cd, "cd_x100", yC, c2, true);

  // legend
  ctx.textBaseline = "middle";
  ctx.textAlign = "left";
  let lx = pad.l;
  const entries = [];
  if (yP) entries.push([c1, "PSNR (dB, higher is better)", false]);
  if (yC) entries.push([c2, `Chamfer ×10² (lower is better)${yP ? ", right axis" : ""}`, true]);
  for (const [color, name, dashed] of entries) {
    ctx.strokeStyle = color;
    ctx.lineWidth = 2;
    ctx.setLineDash(dashed ? [6, 4] : []);
    ctx.beginPath(); ctx.moveTo(lx, 12); ctx.lineTo(lx + 18, 12); ctx.stroke();
    ctx.setLineDash([]);
    ctx.fillStyle = text;
    ctx.fillText(name, lx + 24, 12);
    lx += 24 + ctx.measureText(name).width + 20;
  }
  return { psnr: ps.length, cd: cd.length };
}
