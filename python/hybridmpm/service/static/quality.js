// The quality the page draws at, and the controller that keeps its frame rate (no WebGL here: app.js hands the
// chosen level to the renderer).
//
// A level sets the pixels drawn per device pixel (`scale`), and what the fluid passes cost: the water splatted as
// every particle or one splat per cell of `lod` grid cells (cells.js), the passes' resolution as a share of the
// scene's own (`fluid`), the depth blur's taps each side (`taps`). On software GL the splats are most of a frame:
// their number first, then their pixels.
//
// Auto: the page measures how fast it can draw, from requestAnimationFrame's timestamps: the interval after each
// callback that drew (the browser calls it again when the frame is done; drawing every callback, that is the frame
// rate). Per window of WINDOW_MS (at least MIN_SAMPLES draws) the mean interval gives the frames/s it can draw (the
// mean, not the median: the intervals come in multiples of the display's 16.7 ms, and a page drawing 26 frames/s
// alternates 33 and 50 ms: its median says 20 or 30). An interval over STALL_MS is a stall (a hidden tab), not kept.
// Under TARGET_FPS: one level down (or two when under half the target). Over UP_FPS, and over UP_MARGIN × TARGET_FPS
// once scaled by the next level's cost, for UP_HOLD_MS: one level up, unless that level fell under the target less
// than its back-off ago (BACKOFF_MS, doubled each time it falls again): the hysteresis that keeps it from stepping
// up and down. Fixed: the level the user chose, measured the
// same way, never changed.

export const TARGET_FPS = 24;       // frames/s drawn the page keeps
export const UP_FPS = 40;           // frames/s it must reach to try a level up (and UP_MARGIN × TARGET_FPS predicted there)
export const WINDOW_MS = 1500;      // one measurement
export const STALL_MS = 2000;       // an interval this long is not a frame
export const MIN_SAMPLES = 3;       // draws a measurement needs
export const SETTLE_MS = 300;       // after a change, not measured (targets are made again, the canvas resized)
export const UP_HOLD_MS = 3000;     // over UP_FPS this long before a level up
export const BACKOFF_MS = 8000;     // a level that fell under the target is not tried again for this long (doubling)

// Cheapest first. `cost`: browser CPU per frame relative to the cheapest, measured on the default 3D scene 300 frames
// in (the water spread over the floor), software GL: `python benchmarks/bench_page.py --ladder 3 --advance 300`
// (benchmarks/results/page_quality_levels.md); a level up is tried only where the measured frame rate scaled by it
// stays over UP_MARGIN × TARGET_FPS. The cheapest, a third of the pixels and 3-cell splats, is for CPUs slower than
// the development machine (a 2-core Zen 3 drew 15.7 frames/s at the next one with a jelly in).
export const LEVELS = [
  { scale: 0.35, lod: 3, fluid: 0.75, taps: 2, cost: 1, label: "1/3 px, water in 3-cell splats at 3/4" },
  { scale: 0.5, lod: 2, fluid: 0.75, taps: 3, cost: 1.6, label: "1/2 px, water in 2-cell splats at 3/4" },
  { scale: 0.5, lod: 2, fluid: 1, taps: 4, cost: 2, label: "1/2 px, water in 2-cell splats" },
  { scale: 0.5, lod: 1, fluid: 1, taps: 6, cost: 2.8, label: "1/2 px, water in cell splats" },
  { scale: 0.75, lod: 1, fluid: 0.75, taps: 4, cost: 3.8, label: "3/4 px, water in cell splats at 3/4" },
  { scale: 0.75, lod: 1, fluid: 1, taps: 6, cost: 5.2, label: "3/4 px, water in cell splats" },
  { scale: 0.75, lod: 0, fluid: 1, taps: 6, cost: 9.7, label: "3/4 px, every particle splatted" },
  { scale: 1, lod: 0, fluid: 1, taps: 6, cost: 13.6, label: "full, every particle splatted" },
];
export const SOFTWARE_START = 4;    // software GL starts in the middle (3/4 px, cell splats); a GPU at the top
export const UP_MARGIN = 1.25;

// The highest level drawn at `scale` or less (the `?scale=` preset: the fluid passes' full cost at that resolution)
export function levelForScale(scale) {
  let best = 0;
  LEVELS.forEach((l, i) => { if (l.scale <= scale + 1e-9) best = i; });
  return best;
}

export class QualityController {
  // apply(level, index): sets the renderer; start: the first level's index; auto: whether it adapts; clock: the
  // milliseconds frame() is given (requestAnimationFrame's timestamps are performance.now()'s)
  constructor(apply, start, auto = true, clock = () => performance.now()) {
    this.apply = apply; this.auto = auto; this.level = start; this.clock = clock;
    this.fps = 0;                   // frames/s the page could draw, the last measurement
    this.changes = [];              // {t, from, to, fps, why}
    this.failed = LEVELS.map(() => ({ at: -Infinity, backoff: BACKOFF_MS / 2 }));
    this.prev = null; this.prevDrew = false; this.samples = [];
    this.windowStart = 0; this.settleUntil = 0; this.upSince = null;
    apply(LEVELS[start], start);
  }

  setAuto(on) { this.auto = on; this.upSince = null; }

  // on: not measured (the page draws something else: a GIF); off: measured again after SETTLE_MS
  hold(on) {
    const now = this.clock();
    this.samples = []; this.upSince = null;
    this.settleUntil = on ? Infinity : now + SETTLE_MS; this.windowStart = on ? Infinity : now + SETTLE_MS;
  }

  // a fixed level, from the user (auto off)
  fix(index) { this.auto = false; this.set(index, this.clock(), "fixed"); }

  set(index, now, why) {
    index = Math.max(0, Math.min(LEVELS.length - 1, index));
    if (index === this.level) return;
    this.changes.push({ t: now, from: this.level, to: index, fps: this.fps, why });
    if (this.changes.length > 50) this.changes.shift();
    this.level = index;
    this.apply(LEVELS[index], index);
    this.samples = []; this.upSince = null; this.settleUntil = now + SETTLE_MS; this.windowStart = now + SETTLE_MS;
  }

  // every animation frame: its timestamp, and whether the page drew in it
  frame(now, drew) {
    const prev = this.prev, prevDrew = this.prevDrew;
    this.prev = now; this.prevDrew = drew;
    if (prev === null || !prevDrew || prev < this.settleUntil) return;
    if (!this.samples.length && now - this.windowStart > WINDOW_MS) this.windowStart = prev;
    if (now - prev > STALL_MS) return;
    this.samples.push(now - prev);
    if (now - this.windowStart < WINDOW_MS || this.samples.length < MIN_SAMPLES) {
      if (now - this.windowStart > 5 * WINDOW_MS) { this.samples = []; this.windowStart = now; } // too few draws: start again
      return;
    }
    this.fps = (1000 * this.samples.length) / this.samples.reduce((a, b) => a + b, 0);
    this.samples = []; this.windowStart = now;
    if (this.auto) this.decide(now);
  }

  decide(now) {
    const L = this.level;
    if (this.fps < TARGET_FPS) {
      this.upSince = null;
      if (L === 0) return;
      const f = this.failed[L];
      f.backoff = now - f.at < 2 * f.backoff ? 2 * f.backoff : BACKOFF_MS; // fell again soon after trying it: wait longer
      f.at = now;
      this.set(L - (this.fps < TARGET_FPS / 2 && L > 1 ? 2 : 1), now, "down");
      return;
    }
    const predicted = L < LEVELS.length - 1 ? (this.fps * LEVELS[L].cost) / LEVELS[L + 1].cost : 0;
    if (this.fps < UP_FPS || predicted < UP_MARGIN * TARGET_FPS) { this.upSince = null; return; }
    if (this.upSince === null) { this.upSince = now; return; }
    const f = this.failed[L + 1];
    if (now - this.upSince >= UP_HOLD_MS && now - f.at >= f.backoff) this.set(L + 1, now, "up");
  }

  // what the page shows: "4/6 auto"
  describe() { return `${this.level + 1}/${LEVELS.length} ${this.auto ? "auto" : "fixed"}`; }

  state() {
    return { level: this.level, levels: LEVELS.length, auto: this.auto, fps: this.fps, settings: LEVELS[this.level], changes: this.changes.slice() };
  }
}
