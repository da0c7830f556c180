// A small rolling chart (2D canvas) of knee flexion: the last WINDOW_S seconds of each series (a leg's capacitive
// sleeve through the flex model, a leg's knee in the IMU pose), each drawn against its own sample rate.
const WINDOW_S = 10;
const COLOURS = { Left: "#2563eb", Right: "#ea580c" };

export class KneeChart {
  constructor(canvas) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.series = {}; // label -> {side, rateHz, dashed, values}
    this.pending = false;
    canvas.dataset.series = "";
    this.ctx.clearRect(0, 0, canvas.width, canvas.height);
  }

  // values: the newest samples of the series `label` (a leg `side`, at `rateHz`; `dashed`: the IMU pose's)
  push(label, side, rateHz, values, dashed = false) {
    if (!values.length) return;
    const s = (this.series[label] ??= { side, rateHz, dashed, values: [] });
    s.values.push(...values);
    const n = Math.round(WINDOW_S * rateHz);
    if (s.values.length > n) s.values.splice(0, s.values.length - n);
    this.canvas.dataset.series = Object.keys(this.series).join("|");
    if (!this.pending) requestAnimationFrame(() => this.draw());
    this.pending = true;
  }

  draw() {
    this.pending = false;
    const { ctx, canvas } = this;
    const [W, H, left, top] = [canvas.width, canvas.height, 36, 30];
    const all = Object.values(this.series).flatMap((s) => s.values);
    const lo = Math.floor(Math.min(0, ...all) / 10) * 10;
    const hi = Math.ceil(Math.max(10, ...all) / 10) * 10;
    const y = (v) => H - 4 - ((H - top - 8) * (v - lo)) / (hi - lo);
    ctx.clearRect(0, 0, W, H);
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillStyle = "#555";
    ctx.strokeStyle = "#ddd";
    ctx.setLineDash([]);
    for (const v of [lo, (lo + hi) / 2, hi]) {
      ctx.fillText(`${v}°`, 2, y(v) + 4);
      ctx.beginPath();
      ctx.moveTo(left, y(v));
      ctx.lineTo(W, y(v));
      ctx.stroke();
    }
    ctx.fillText(`last ${WINDOW_S} s`, W - 60, H - 6);
    Object.entries(this.series).forEach(([label, s], k) => {
      const n = Math.round(WINDOW_S * s.rateHz);
      ctx.strokeStyle = ctx.fillStyle = COLOURS[s.side];
      ctx.setLineDash(s.dashed ? [5, 3] : []);
      ctx.beginPath();
      s.values.forEach((v, i) => ctx.lineTo(left + ((W - left) * (i + n - s.values.length)) / n, y(v)));
      ctx.stroke();
      ctx.fillText(`${label} ${s.values.at(-1).toFixed(0)}°`, left + 4 + 170 * (k % 4), 12 + 13 * Math.floor(k / 4));
    });
    ctx.setLineDash([]);
  }
}
