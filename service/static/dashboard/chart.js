// A small rolling chart (2D canvas) of one angle per leg: the last WINDOW_S seconds of the flex answers.
const WINDOW_S = 10;
const COLOURS = { Left: "#2563eb", Right: "#ea580c" };

export class FlexChart {
  constructor(canvas, rateHz) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.n = Math.round(WINDOW_S * rateHz);
    this.series = {};
    this.pending = false;
  }

  push(side, values) {
    const s = (this.series[side] ??= []);
    s.push(...values);
    if (s.length > this.n) s.splice(0, s.length - this.n);
    if (!this.pending) requestAnimationFrame(() => this.draw());
    this.pending = true;
  }

  draw() {
    this.pending = false;
    const { ctx, canvas, n } = this;
    const [W, H, left, top] = [canvas.width, canvas.height, 36, 18];
    const all = Object.values(this.series).flat();
    const lo = Math.floor(Math.min(0, ...all) / 10) * 10;
    const hi = Math.ceil(Math.max(10, ...all) / 10) * 10;
    const y = (v) => H - 4 - ((H - top - 8) * (v - lo)) / (hi - lo);
    ctx.clearRect(0, 0, W, H);
    ctx.font = "11px system-ui, sans-serif";
    ctx.fillStyle = "#555";
    ctx.strokeStyle = "#ddd";
    for (const v of [lo, (lo + hi) / 2, hi]) {
      ctx.fillText(`${v}°`, 2, y(v) + 4);
      ctx.beginPath();
      ctx.moveTo(left, y(v));
      ctx.lineTo(W, y(v));
      ctx.stroke();
    }
    ctx.fillText(`last ${WINDOW_S} s`, W - 60, H - 6);
    Object.entries(this.series).forEach(([side, s], k) => {
      ctx.strokeStyle = ctx.fillStyle = COLOURS[side];
      ctx.beginPath();
      s.forEach((v, i) => ctx.lineTo(left + ((W - left) * (i + n - s.length)) / n, y(v)));
      ctx.stroke();
      ctx.fillText(`${side} knee ${s.at(-1).toFixed(0)}°`, left + 4 + 110 * k, 12);
    });
  }
}
