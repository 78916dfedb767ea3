// A small animated-GIF encoder (GIF89a): one fixed 6×7×6 colour cube with ordered dithering (no
// palette search, so every frame shares one global table), LZW-compressed, looping forever.

const LEVELS = [6, 7, 6];
const BAYER = [0, 8, 2, 10, 12, 4, 14, 6, 3, 11, 1, 9, 15, 7, 13, 5].map((v) => (v + 0.5) / 16 - 0.5);

function palette() {
  const p = new Uint8Array(256 * 3);
  let i = 0;
  for (let r = 0; r < LEVELS[0]; r++) for (let g = 0; g < LEVELS[1]; g++) for (let b = 0; b < LEVELS[2]; b++) {
    p[i++] = Math.round((255 * r) / (LEVELS[0] - 1));
    p[i++] = Math.round((255 * g) / (LEVELS[1] - 1));
    p[i++] = Math.round((255 * b) / (LEVELS[2] - 1));
  }
  return p;
}

// RGBA pixels → palette indices (ordered dithering)
function indices(rgba, w, h) {
  const out = new Uint8Array(w * h);
  const s0 = (LEVELS[0] - 1) / 255, s1 = (LEVELS[1] - 1) / 255, s2 = (LEVELS[2] - 1) / 255;
  for (let y = 0; y < h; y++) for (let x = 0; x < w; x++) {
    const i = y * w + x, d = BAYER[(y & 3) * 4 + (x & 3)];
    const r = Math.min(LEVELS[0] - 1, Math.max(0, Math.round(rgba[4 * i] * s0 + d)));
    const g = Math.min(LEVELS[1] - 1, Math.max(0, Math.round(rgba[4 * i + 1] * s1 + d)));
    const b = Math.min(LEVELS[2] - 1, Math.max(0, Math.round(rgba[4 * i + 2] * s2 + d)));
    out[i] = (r * LEVELS[1] + g) * LEVELS[2] + b;
  }
  return out;
}

class Bytes {
  constructor() { this.buf = new Uint8Array(1 << 16); this.n = 0; }
  byte(b) {
    if (this.n === this.buf.length) { const nb = new Uint8Array(this.buf.length * 2); nb.set(this.buf); this.buf = nb; }
    this.buf[this.n++] = b;
  }
  bytes(arr) { for (const b of arr) this.byte(b); }
  u16(v) { this.byte(v & 255); this.byte((v >> 8) & 255); }
  result() { return this.buf.subarray(0, this.n); }
}

// LZW with variable code width (GIF flavour), written as data sub-blocks
function lzw(out, idx, minCode) {
  const clear = 1 << minCode, eoi = clear + 1;
  let size = minCode + 1, next = eoi + 1;
  const dict = new Map();
  let cur = 0, bits = 0;
  const block = [];
  const emit = (code) => {
    cur |= code << bits; bits += size;
    while (bits >= 8) {
      block.push(cur & 255); cur >>>= 8; bits -= 8;
      if (block.length === 255) { out.byte(255); out.bytes(block); block.length = 0; }
    }
  };
  out.byte(minCode);
  emit(clear);
  let prefix = idx[0];
  for (let i = 1; i < idx.length; i++) {
    const k = idx[i], key = prefix * 256 + k, hit = dict.get(key);
    if (hit !== undefined) { prefix = hit; continue; }
    emit(prefix);
    if (next < 4096) {
      dict.set(key, next++);
      if (next > 1 << size && size < 12) size++;
    } else {
      emit(clear); dict.clear(); size = minCode + 1; next = eoi + 1;
    }
    prefix = k;
  }
  emit(prefix);
  emit(eoi);
  if (bits > 0) block.push(cur & 255);
  if (block.length) { out.byte(block.length); out.bytes(block); }
  out.byte(0);
}

// Encode frames (RGBA Uint8ClampedArray of w×h each) as one looping GIF; `delayCs` per frame [1/100 s].
// `onFrame(i)` is awaited after each frame (a progress hook that can yield to the page).
export async function encodeGif(frames, w, h, delayCs, onFrame = null) {
  const out = new Bytes();
  out.bytes([71, 73, 70, 56, 57, 97]); // GIF89a
  out.u16(w); out.u16(h);
  out.byte(0xf7); out.byte(0); out.byte(0); // global table of 256 colours
  out.bytes(palette());
  out.bytes([0x21, 0xff, 11, ...[..."NETSCAPE2.0"].map((c) => c.charCodeAt(0)), 3, 1, 0, 0, 0]); // loop forever
  for (let f = 0; f < frames.length; f++) {
    out.bytes([0x21, 0xf9, 4, 0x04]); out.u16(delayCs); out.byte(0); out.byte(0); // graphic control: keep, delay
    out.byte(0x2c); out.u16(0); out.u16(0); out.u16(w); out.u16(h); out.byte(0);
    lzw(out, indices(frames[f], w, h), 8);
    if (onFrame) await onFrame(f);
  }
  out.byte(0x3b);
  return out.result();
}
