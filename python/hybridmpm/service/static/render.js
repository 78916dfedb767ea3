// The WebGL2 view of a session (hand-written, no library): the domain's walls and obstacles as solids,
// particles as shaded sprites with depth, and the "fluid" look: water as a surface (3D: screen-space
// fluid rendering — a depth and a thickness splat of the particles, a bilateral blur of the depth,
// shading from the normal reconstructed from it; 2D: a density field splatted and thresholded), sand as
// grains. Canvas2DRenderer is the fallback where WebGL2 (or a float render target) is missing.

import { Lattice, PER_CELL, cellSplats, surfaceIndices } from "./cells.js";
import { Camera, dot, invert, transform4 } from "./mat.js";

const WATER = 5, SAND = 6, WALL = 3, MUD = 7, JELLY = 8, SNOW = 9;
// [MPM, network] per material: the frame's solver tints the particles (the legend's colours); the solids
// (jelly translucent, snow white, mud brown) run on MPM only
export const COLORS = {
  [WATER]: ["#1f5fd1", "#19b5c9"],
  [SAND]: ["#b8862e", "#e3c44a"],
  [WALL]: ["#6b7280", "#6b7280"],
  [MUD]: ["#6b4226", "#6b4226"],
  [JELLY]: ["#e0457b", "#e0457b"],
  [SNOW]: ["#f7f9fc", "#f7f9fc"],
};
export const JELLY_ALPHA = 0.55;
const rgb = (hex) => [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);

// ------------------------------------------------------------------ shaders
const SPRITE_VS = `#version 300 es
layout(location = 0) in vec3 a_pos;
layout(location = 1) in vec2 a_info;          // GNS type, particle index (a cell's splat: its particle count)
uniform mat4 u_view, u_proj;
uniform float u_pointScale, u_radius;
uniform float u_lod;                           // > 0: splats of cells of this many particles at rest
uniform vec3 u_mask;                           // draw water, sand and the solids, boundary
uniform float u_jellyPass;                     // 0: all but jelly, 1: jelly only (translucent, drawn last)
uniform vec3 u_boxLo, u_boxHi;                 // the box the water rests in (CLIP, below)
uniform float u_clip;
out float v_type; out float v_seed; out vec3 v_viewPos; out float v_radius;
flat out float v_clip;                         // the sphere pokes through a wall face: its fragments are clipped
float hash(float x) { return fract(sin(x * 12.9898) * 43758.5453); }
void main() {
  float t = a_info.x;
  float on = t == 5.0 ? u_mask.x : (t == 3.0 ? u_mask.z : u_mask.y);
  if ((t == 8.0) != (u_jellyPass > 0.5)) on = 0.0;
  vec4 vp = u_view * vec4(a_pos, 1.0);
  gl_Position = u_proj * vp;
  float r = u_radius * (t == 6.0 ? 0.78 + 0.4 * hash(a_info.y) : 1.0);
  if (u_lod > 0.0) r *= clamp(pow(a_info.y / u_lod, 1.0 / 3.0), 0.5, 1.0); // a cell's splat: a_info.y its particles
  gl_PointSize = max(1.0, 2.0 * r * u_pointScale / gl_Position.w);
  if (on < 0.5) gl_Position = vec4(2.0, 2.0, 2.0, 1.0);
  v_clip = u_clip > 0.5 && (any(lessThan(a_pos - r, u_boxLo)) || any(greaterThan(a_pos + r, u_boxHi))) ? 1.0 : 0.0;
  v_type = t; v_seed = a_info.y; v_viewPos = vp.xyz; v_radius = r;
}`;

// shaded spheres: plain particles, and sand grains in the fluid look
const SPRITE_FS = `#version 300 es
precision highp float;
in float v_type; in float v_seed; in vec3 v_viewPos; in float v_radius;
uniform vec3 u_water, u_sand, u_wall, u_mud, u_jelly, u_snow;
uniform float u_grain;                          // colour jitter of sand grains
uniform float u_alpha;                          // the jelly pass's opacity
out vec4 o;
float hash(float x) { return fract(sin(x * 78.233) * 43758.5453); }
void main() {
  vec2 c = gl_PointCoord * 2.0 - 1.0; c.y = -c.y;
  float d2 = dot(c, c);
  if (d2 > 1.0) discard;
  vec3 n = vec3(c, sqrt(1.0 - d2));
  vec3 base = v_type == 5.0 ? u_water : (v_type == 6.0 ? u_sand : (v_type == 7.0 ? u_mud : (v_type == 8.0 ? u_jelly : (v_type == 9.0 ? u_snow : u_wall))));
  if (v_type == 6.0) base *= 1.0 + u_grain * (hash(v_seed) - 0.5);
  vec3 L = normalize(vec3(-0.4, 0.7, 0.6));
  float diff = max(dot(n, L), 0.0);
  float spec = pow(max(dot(n, normalize(L + vec3(0.0, 0.0, 1.0))), 0.0), 36.0);
  o = vec4(base * (0.38 + 0.62 * diff) + 0.22 * spec, u_alpha);
}`;

// 3D water: the part [s0, s1] of a sprite's chord inside the box the water rests in (s along the view's +z, in
// [-h, h] around the particle's centre): a sphere of the splat pokes through a wall face by up to its radius, so
// the surface ends flat at the wall (the glass of a tank), not in a row of bumps. u_clip = 0: the whole chord.
const CLIP = `
uniform mat4 u_viewInv;
uniform vec3 u_boxLo, u_boxHi;
flat in float v_clip;
bool chord(vec2 c, float h, out float s0, out float s1) {
  s0 = -h; s1 = h;
  if (v_clip < 0.5) return true;                // the whole sphere is inside the box (decided per splat)
  vec3 A = (u_viewInv * vec4(v_viewPos + vec3(c.x, -c.y, 0.0) * v_radius, 1.0)).xyz;
  vec3 F = u_viewInv[2].xyz;
  for (int k = 0; k < 3; k++) {
    if (abs(F[k]) < 1e-6) {
      if (A[k] < u_boxLo[k] || A[k] > u_boxHi[k]) return false;
      continue;
    }
    float t0 = (u_boxLo[k] - A[k]) / F[k], t1 = (u_boxHi[k] - A[k]) / F[k];
    s0 = max(s0, min(t0, t1)); s1 = min(s1, max(t0, t1));
  }
  return s0 < s1;
}`;

// the water's view-space depth (distance along the view axis, sphere-corrected)
const DEPTH_FS = `#version 300 es
precision highp float;
in float v_type; in float v_seed; in vec3 v_viewPos; in float v_radius;
out vec4 o;
${CLIP}
void main() {
  vec2 c = gl_PointCoord * 2.0 - 1.0;
  float d2 = dot(c, c);
  if (d2 > 1.0) discard;
  float s0, s1;
  if (!chord(c, sqrt(1.0 - d2) * v_radius, s0, s1)) discard;
  o = vec4(-v_viewPos.z - s1, 0.0, 0.0, 1.0);
}`;

// thickness (3D: the sphere's chord) or density (2D: a smooth kernel), added up
const THICK_FS = `#version 300 es
precision highp float;
in float v_type; in float v_seed; in vec3 v_viewPos; in float v_radius;
uniform float u_kernel;                         // 0: chord [m], 1: density kernel
out vec4 o;
${CLIP}
void main() {
  vec2 c = gl_PointCoord * 2.0 - 1.0;
  float d2 = dot(c, c);
  if (d2 > 1.0) discard;
  float s0, s1;
  if (!chord(c, sqrt(1.0 - d2) * v_radius, s0, s1)) discard;
  float v = u_kernel > 0.5 ? (1.0 - d2) * (1.0 - d2) : s1 - s0;
  o = vec4(v, 0.0, 0.0, 1.0);
}`;

// depth (kept by MIN blending) and thickness (added) in one pass, two render targets
const SPLAT_FS = `#version 300 es
precision highp float;
in float v_type; in float v_seed; in vec3 v_viewPos; in float v_radius;
uniform float u_depthFrac;                      // the depth sphere's radius / the sprite's
layout(location = 0) out vec4 o_depth;
layout(location = 1) out vec4 o_thick;
${CLIP}
void main() {
  vec2 c = gl_PointCoord * 2.0 - 1.0;
  float d2 = dot(c, c);
  if (d2 > 1.0) discard;
  float s0, s1;
  if (!chord(c, sqrt(1.0 - d2) * v_radius, s0, s1)) discard;
  o_thick = vec4(s1 - s0, 0.0, 0.0, 1.0);
  float e2 = d2 / (u_depthFrac * u_depthFrac);
  float front = min(s1, sqrt(max(0.0, 1.0 - e2)) * v_radius * u_depthFrac);
  o_depth = vec4(e2 < 1.0 && front > s0 ? -v_viewPos.z - front : 1e4, 0.0, 0.0, 1.0);
}`;

const QUAD_VS = `#version 300 es
void main() {
  vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}`;

// separable bilateral blur of the depth (edges kept: weights fall off with the depth difference)
const BLUR_FS = `#version 300 es
precision highp float;
const float FAR = 1000.0;                       // no water (the one-pass splat clears to 1e4)
uniform sampler2D u_tex;
uniform vec2 u_dir;
uniform float u_step, u_falloff;
uniform int u_taps;                             // taps each side: fewer, farther apart, over the same span
out vec4 o;
void main() {
  ivec2 size = textureSize(u_tex, 0);
  ivec2 p = ivec2(gl_FragCoord.xy);
  float d = texelFetch(u_tex, p, 0).r;
  if (d <= 0.0 || d > FAR) { o = vec4(0.0); return; }
  float sum = 0.0, wsum = 0.0, k = 6.0 / float(u_taps);
  for (int i = -u_taps; i <= u_taps; i++) {
    float x = float(i) * k;                     // in the 6-tap kernel's units (Gaussian, sigma 3)
    ivec2 q = clamp(p + ivec2(u_dir * x * u_step), ivec2(0), size - 1);
    float s = texelFetch(u_tex, q, 0).r;
    if (s <= 0.0 || s > FAR) continue;
    float ws = exp(-x * x / 18.0);
    float dz = (s - d) * u_falloff;
    float w = ws * exp(-dz * dz);
    sum += s * w; wsum += w;
  }
  o = vec4(sum / wsum, 0.0, 0.0, 1.0);
}`;

// 3D water: normal from the blurred depth, Fresnel reflection of a sky, absorption by thickness
const SURFACE_FS = `#version 300 es
precision highp float;
uniform sampler2D u_depth, u_thick;
uniform mat4 u_proj;
uniform mat3 u_viewInv;
uniform vec2 u_viewport;
uniform vec3 u_water;
out vec4 o;
vec3 viewPos(vec2 uv, float d) {
  vec2 ndc = uv * 2.0 - 1.0;
  return vec3(ndc.x * d / u_proj[0][0], ndc.y * d / u_proj[1][1], -d);
}
vec3 at(vec2 uv) { return viewPos(uv, texture(u_depth, uv).r); }
void main() {
  vec2 uv = gl_FragCoord.xy / u_viewport;
  float d = texture(u_depth, uv).r;
  if (d <= 0.0) discard;
  vec2 texel = 1.0 / vec2(textureSize(u_depth, 0));
  vec3 P = viewPos(uv, d);
  vec3 px = at(uv + vec2(texel.x, 0.0)) - P, mx = P - at(uv - vec2(texel.x, 0.0));
  vec3 py = at(uv + vec2(0.0, texel.y)) - P, my = P - at(uv - vec2(0.0, texel.y));
  vec3 ddx = abs(px.z) < abs(mx.z) ? px : mx;
  vec3 ddy = abs(py.z) < abs(my.z) ? py : my;
  vec3 n = normalize(cross(ddx, ddy));
  if (n.z < 0.0) n = -n;
  float t = texture(u_thick, uv).r;
  vec3 V = normalize(-P);
  vec3 L = normalize(vec3(-0.35, 0.75, 0.55));
  float fres = 0.03 + 0.97 * pow(1.0 - max(dot(n, V), 0.0), 5.0);
  vec3 R = u_viewInv * reflect(-V, n);
  vec3 sky = mix(vec3(0.80, 0.86, 0.93), vec3(0.42, 0.60, 0.86), clamp(R.y * 1.4, 0.0, 1.0));
  float spec = pow(max(dot(n, normalize(L + V)), 0.0), 90.0);
  float diff = max(dot(n, L), 0.0);
  vec3 absorb = exp(-min(t, 0.3) * vec3(9.0, 3.2, 1.6)); // deeper than 0.3 m: the same deep blue, not black
  vec3 body = u_water * (0.55 + 0.45 * diff) * mix(vec3(0.55), vec3(1.15), absorb);
  vec3 col = mix(body, sky, fres) + 0.9 * spec;
  float a = clamp(1.0 - exp(-t * 60.0), 0.35, 0.94);
  o = vec4(col * a, a);
}`;

// the shaded surface (premultiplied, at the fluid passes' resolution) laid over the frame, filtered up
const BLIT_FS = `#version 300 es
precision highp float;
uniform sampler2D u_tex;
uniform vec2 u_viewport;
out vec4 o;
void main() { o = texture(u_tex, gl_FragCoord.xy / u_viewport); }`;

// 2D water: the thresholded density field, shaded from its gradient
const FIELD_FS = `#version 300 es
precision highp float;
uniform sampler2D u_thick;
uniform vec2 u_viewport;
uniform vec3 u_water;
uniform float u_level;
out vec4 o;
void main() {
  vec2 uv = gl_FragCoord.xy / u_viewport;
  float f = texture(u_thick, uv).r;
  if (f < 0.6 * u_level) discard;
  vec2 texel = 1.0 / vec2(textureSize(u_thick, 0));
  float gx = texture(u_thick, uv + vec2(texel.x, 0.0)).r - texture(u_thick, uv - vec2(texel.x, 0.0)).r;
  float gy = texture(u_thick, uv + vec2(0.0, texel.y)).r - texture(u_thick, uv - vec2(0.0, texel.y)).r;
  float deep = smoothstep(u_level, 2.6 * u_level, f);
  vec3 n = normalize(vec3(-gx, -gy, 0.6 * u_level) * vec3(1.0 - deep, 1.0 - deep, 1.0));
  vec3 L = normalize(vec3(-0.4, 0.6, 0.7));
  float edge = smoothstep(0.75 * u_level, 1.0 * u_level, f);
  vec3 body = mix(u_water * 1.3 + 0.16, u_water * 0.8, deep);
  float spec = pow(max(dot(n, normalize(L + vec3(0.0, 0.0, 1.0))), 0.0), 40.0);
  float rim = 1.0 - n.z;
  vec3 col = body * (0.75 + 0.25 * max(dot(n, L), 0.0)) + 0.5 * spec + 0.45 * rim;
  float a = edge * 0.92;
  o = vec4(col * a, a);
}`;

// solids: the domain's walls (drawn from inside in 3D, a grid on them) and the obstacles
const SOLID_VS = `#version 300 es
layout(location = 0) in vec3 a_pos;
layout(location = 1) in vec3 a_nrm;
uniform mat4 u_viewProj, u_model;
out vec3 v_n; out vec3 v_w;
void main() {
  vec4 w = u_model * vec4(a_pos, 1.0);
  v_w = w.xyz; v_n = mat3(u_model) * a_nrm;
  gl_Position = u_viewProj * w;
}`;
const SOLID_FS = `#version 300 es
precision highp float;
in vec3 v_n; in vec3 v_w;
uniform vec3 u_color;
uniform float u_grid, u_lit;
out vec4 o;
void main() {
  vec3 n = normalize(v_n);
  vec3 L = normalize(vec3(0.35, 0.9, 0.55));
  vec3 col = u_lit > 0.5 ? u_color * (0.62 + 0.38 * max(dot(n, L), 0.0) + 0.12 * max(dot(n, -L), 0.0)) : u_color;
  if (u_grid > 0.0) { // grid lines on the walls, in the two directions along each face (no derivatives: cheap in software GL)
    vec3 line = abs(fract(v_w * u_grid - 0.5) - 0.5);
    vec3 along = step(abs(n), vec3(0.5));
    float m = min(min(along.x > 0.5 ? line.x : 1.0, along.y > 0.5 ? line.y : 1.0), along.z > 0.5 ? line.z : 1.0);
    col *= m < 0.02 ? 0.86 : 1.0;
  }
  o = vec4(col, 1.0);
}`;
const LINE_FS = `#version 300 es
precision highp float;
uniform vec3 u_color;
out vec4 o;
void main() { o = vec4(u_color, 1.0); }`;

// ------------------------------------------------------------------ meshes
// a unit cube [-1, 1]³ as triangles with normals; `inward`: wound and lit from inside (a room)
function cube(inward) {
  const out = [];
  const faces = [[0, 1], [0, -1], [1, 1], [1, -1], [2, 1], [2, -1]];
  for (const [ax, s] of faces) {
    const u = (ax + 1) % 3, v = (ax + 2) % 3;
    const corner = (a, b) => { const p = [0, 0, 0]; p[ax] = s; p[u] = a; p[v] = b; return p; };
    let quad = [corner(-1, -1), corner(1, -1), corner(1, 1), corner(-1, -1), corner(1, 1), corner(-1, 1)];
    if ((s < 0) !== inward) quad = [quad[0], quad[2], quad[1], quad[3], quad[5], quad[4]];
    const n = [0, 0, 0]; n[ax] = inward ? -s : s;
    for (const p of quad) out.push(...p, ...n);
  }
  return new Float32Array(out);
}
function sphere(lat = 14, lon = 24) {
  const out = [];
  const pt = (i, j) => {
    const th = (Math.PI * i) / lat, ph = (2 * Math.PI * j) / lon;
    return [Math.sin(th) * Math.cos(ph), Math.cos(th), -Math.sin(th) * Math.sin(ph)];
  };
  for (let i = 0; i < lat; i++) for (let j = 0; j < lon; j++) {
    const a = pt(i, j), b = pt(i + 1, j), c = pt(i + 1, j + 1), d = pt(i, j + 1);
    for (const p of [a, b, c, a, c, d]) out.push(...p, ...p);
  }
  return new Float32Array(out);
}
function disc(seg = 40) {
  const out = [];
  for (let j = 0; j < seg; j++) {
    const a = (2 * Math.PI * j) / seg, b = (2 * Math.PI * (j + 1)) / seg;
    out.push(0, 0, 0, 0, 0, 1, Math.cos(a), Math.sin(a), 0, 0, 0, 1, Math.cos(b), Math.sin(b), 0, 0, 0, 1);
  }
  return new Float32Array(out);
}
const SQUARE = new Float32Array([-1, -1, 0, 0, 0, 1, 1, -1, 0, 0, 0, 1, 1, 1, 0, 0, 0, 1, -1, -1, 0, 0, 0, 1, 1, 1, 0, 0, 0, 1, -1, 1, 0, 0, 0, 1]);
const BOX_EDGES = (() => {
  const c = [];
  for (let a = 0; a < 3; a++) for (const s of [-1, 1]) for (const t of [-1, 1]) {
    const p = [0, 0, 0], q = [0, 0, 0], u = (a + 1) % 3, v = (a + 2) % 3;
    p[a] = -1; q[a] = 1; p[u] = q[u] = s; p[v] = q[v] = t;
    c.push(...p, 0, 1, 0, ...q, 0, 1, 0);
  }
  return new Float32Array(c);
})();

// column-major model matrix: world = center + R · (scale ⊙ local); R row-major 3×3
function model(center, scaleXYZ, R) {
  const r = R || [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
  const m = new Float32Array(16);
  for (let c = 0; c < 3; c++) for (let row = 0; row < 3; row++) m[c * 4 + row] = r[row][c] * scaleXYZ[c];
  m[12] = center[0]; m[13] = center[1]; m[14] = center[2] || 0; m[15] = 1;
  return m;
}
function rotation(ob, dim) {
  if (ob.rotation) return ob.rotation.map((row) => [...row, 0].slice(0, 3)).concat(dim === 2 ? [[0, 0, 1]] : []).slice(0, 3);
  const a = ((ob.angle_deg || 0) * Math.PI) / 180;
  return [[Math.cos(a), -Math.sin(a), 0], [Math.sin(a), Math.cos(a), 0], [0, 0, 1]];
}

// The GPU's name, from a throwaway context ("" if it is hidden or there is no WebGL2)
function probeRenderer() {
  const gl = document.createElement("canvas").getContext("webgl2");
  if (!gl) return "";
  const ext = gl.getExtension("WEBGL_debug_renderer_info");
  const name = String(gl.getParameter(ext ? ext.UNMASKED_RENDERER_WEBGL : gl.RENDERER) || "");
  const lose = gl.getExtension("WEBGL_lose_context");
  if (lose) lose.loseContext();
  return name;
}

// ------------------------------------------------------------------ the renderer
export class GLRenderer {
  constructor(canvas) {
    // Software GL (SwiftShader, llvmpipe: headless browsers, machines without a GPU) draws every pixel on the
    // CPU: there the page draws one pixel per CSS pixel and without multisampling.
    this.gpu = probeRenderer();
    this.software = /swiftshader|llvmpipe|softpipe|software/i.test(this.gpu);
    const gl = canvas.getContext("webgl2", { antialias: !this.software, alpha: false, preserveDrawingBuffer: false });
    if (!gl) throw new Error("WebGL2 is not available");
    this.scale = this.software ? 0.75 : 1; // backing pixels per device pixel (the "resolution" setting)
    this.canvas = canvas; this.gl = gl; this.kind = "webgl2";
    this.floatTargets = !!gl.getExtension("EXT_color_buffer_float");
    // depth and thickness in one pass where float targets blend and blend equations are per target
    const floatBlend = gl.getExtension("EXT_float_blend");
    this.indexed = gl.getExtension("OES_draw_buffers_indexed");
    this.onePass = !!(floatBlend && this.indexed);
    this.look = "fluid"; this.showParticles = true; this.fluidScale = 0.5;
    // the quality the page runs at (quality.js sets them): the fluid passes' resolution as a share of the scene's
    // own (fluidScale), the depth blur's taps each side (0: no blur)
    this.fluidFactor = 1; this.blurTaps = 6; this.lod = 0;
    this.splats = null;
    this.surfacesDrawn = 0; // frames whose 3D water was drawn as a surface (the fluid passes to the end)
    this.session = null; this.frame = null; this.camera = new Camera(2);
    const prog = (vs, fs) => {
      const p = gl.createProgram();
      for (const [type, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
        const s = gl.createShader(type);
        gl.shaderSource(s, src); gl.compileShader(s);
        if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`shader: ${gl.getShaderInfoLog(s)}`);
        gl.attachShader(p, s);
      }
      gl.linkProgram(p);
      if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`program: ${gl.getProgramInfoLog(p)}`);
      const u = {};
      for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS); i++) {
        const name = gl.getActiveUniform(p, i).name;
        u[name] = gl.getUniformLocation(p, name);
      }
      return { p, u };
    };
    this.prog = {
      sprite: prog(SPRITE_VS, SPRITE_FS), depth: prog(SPRITE_VS, DEPTH_FS), thick: prog(SPRITE_VS, THICK_FS), splat: prog(SPRITE_VS, SPLAT_FS),
      blur: prog(QUAD_VS, BLUR_FS), surface: prog(QUAD_VS, SURFACE_FS), blit: prog(QUAD_VS, BLIT_FS), field: prog(QUAD_VS, FIELD_FS),
      solid: prog(SOLID_VS, SOLID_FS), line: prog(SOLID_VS, LINE_FS),
    };
    this.meshes = {};
    this.bodies = null; // the rigid bodies' layer (bodies.js), drawn with the obstacles
    for (const [name, data] of Object.entries({ cube: cube(false), room: cube(true), sphere: sphere(), disc: disc(), square: SQUARE, edges: BOX_EDGES })) this.addMesh(name, data);
    this.pvao = gl.createVertexArray(); this.posBuf = gl.createBuffer(); this.infoBuf = gl.createBuffer();
    this.emptyVao = gl.createVertexArray();
    this.targets = null; this.posBytes = 0;
  }

  // a mesh of triangles (Float32Array of position, normal per vertex) under `name` for solid()
  addMesh(name, data) {
    const gl = this.gl, vao = gl.createVertexArray(), buf = gl.createBuffer();
    gl.bindVertexArray(vao); gl.bindBuffer(gl.ARRAY_BUFFER, buf);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0); gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 24, 0);
    gl.enableVertexAttribArray(1); gl.vertexAttribPointer(1, 3, gl.FLOAT, false, 24, 12);
    gl.bindVertexArray(null);
    this.meshes[name] = { vao, count: data.length / 6 };
  }

  get fluidAvailable() { return this.floatTargets; }

  setSession(s) {
    const gl = this.gl;
    this.session = s; this.frame = null;
    this.camera = new Camera(s.dim);
    if (this.splats) { gl.deleteVertexArray(this.splats.vao); gl.deleteBuffer(this.splats.posBuf); gl.deleteBuffer(this.splats.infoBuf); this.splats = null; }
    const info = new Float32Array(2 * s.num_particles);
    s.particle_type.forEach((t, i) => { info[2 * i] = t; info[2 * i + 1] = i; });
    gl.bindVertexArray(this.pvao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.infoBuf); gl.bufferData(gl.ARRAY_BUFFER, info, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(1); gl.vertexAttribPointer(1, 2, gl.FLOAT, false, 0, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.posBuf); gl.bufferData(gl.ARRAY_BUFFER, 4 * s.dim * s.num_particles, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(0); gl.vertexAttribPointer(0, s.dim, gl.FLOAT, false, 0, 0);
    gl.bindVertexArray(null);
    this.hasWater = s.particle_type.includes(WATER);
    // the water's splat radius [particle spacings]: 2 closes the gaps of the paper's sparse scenes (≤ 4096
    // particles); a dense body (the dam break's 23,520) is closed at 1.4, with half the fragments to shade
    this.splat = s.dim === 3 && s.num_fluid > 8192 ? 1.4 : 2.0;
    // a dense 3D body draws only its surface: the interior, hidden behind it, costs software GL most of a frame
    this.cull = s.dim === 3 && s.num_fluid > 8192;
    // and its fluid passes run at a third of the output's resolution (half for the rest): its surface spans
    // most of the canvas, and the blur leaves no detail finer than a few pixels to lose
    this.fluidScale = this.cull ? 0.35 : 0.5;
    this.drawn = s.num_particles;
    if (this.cull) {
      this.idxBuf = this.idxBuf || gl.createBuffer();
      this.indices = new Uint32Array(s.num_particles);
      this.cullCells = new Lattice(s.n_grid || 64, 1, s.num_particles);
      gl.bindVertexArray(this.pvao);
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.idxBuf);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, 4 * s.num_particles, gl.DYNAMIC_DRAW);
      gl.bindVertexArray(null);
    }
    this.hasSand = s.particle_type.includes(SAND);
    this.hasSolid = [MUD, JELLY, SNOW].some((t) => s.particle_type.includes(t));
    this.hasJelly = s.particle_type.includes(JELLY);
  }

  // A frame of the session's particles (false, and nothing changed, for one of another count: a frame after a
  // pour can arrive before the stream's 'particles' event that grows the buffers)
  setFrame(f) {
    if (f.n !== this.session.num_particles) return false;
    this.frame = f;
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.posBuf);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, f.pos);
    if (this.cull) this.surface(f);
    return true;
  }

  // The particles on the surface of the water and every other particle (cells.js): their indices, handed to the GPU.
  surface(f) {
    const m = (this.drawn = surfaceIndices(f.pos, f.n, this.session.particle_type, this.cullCells, this.indices));
    const gl = this.gl;
    gl.bindVertexArray(this.pvao);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.idxBuf);
    gl.bufferSubData(gl.ELEMENT_ARRAY_BUFFER, 0, this.indices, 0, m);
    gl.bindVertexArray(null);
  }

  // The water as one splat per cell of `lod` grid cells (cells.js), for the frame shown; made once per frame and level.
  coarseSplats() {
    const s = this.session, f = this.frame, c = this.lod;
    if (this.splats && this.splats.frame === f && this.splats.c === c) return this.splats;
    const gl = this.gl;
    if (!this.splats || this.splats.c !== c) {
      const lat = new Lattice(s.n_grid || 64, c, s.num_particles, true);
      this.splats = { c, lat, pos: new Float32Array(3 * s.num_fluid), info: new Float32Array(2 * s.num_fluid), vao: this.splats ? this.splats.vao : gl.createVertexArray(),
        posBuf: this.splats ? this.splats.posBuf : gl.createBuffer(), infoBuf: this.splats ? this.splats.infoBuf : gl.createBuffer() };
      gl.bindVertexArray(this.splats.vao);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.splats.posBuf); gl.bufferData(gl.ARRAY_BUFFER, this.splats.pos.byteLength, gl.DYNAMIC_DRAW);
      gl.enableVertexAttribArray(0); gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
      gl.bindBuffer(gl.ARRAY_BUFFER, this.splats.infoBuf); gl.bufferData(gl.ARRAY_BUFFER, this.splats.info.byteLength, gl.DYNAMIC_DRAW);
      gl.enableVertexAttribArray(1); gl.vertexAttribPointer(1, 2, gl.FLOAT, false, 0, 0);
      gl.bindVertexArray(null);
    }
    const S = this.splats;
    S.frame = f;
    S.count = cellSplats(f.pos, f.n, s.particle_type, S.lat, S.pos, S.info);
    gl.bindBuffer(gl.ARRAY_BUFFER, S.posBuf); gl.bufferSubData(gl.ARRAY_BUFFER, 0, S.pos, 0, 3 * S.count);
    gl.bindBuffer(gl.ARRAY_BUFFER, S.infoBuf); gl.bufferSubData(gl.ARRAY_BUFFER, 0, S.info, 0, 2 * S.count);
    return S;
  }

  // the water's splats of the fluid look, with the program `u` in use: every (visible) particle, or one per cell
  // (lod > 0: its radius `lod` grid cells' worth, shrunk with the cube root of how full the cell is)
  waterSplats(u, r) {
    const gl = this.gl, coarse = this.lod > 0 && this.session.dim === 3;
    gl.uniform1f(u.u_radius, this.splat * r * (coarse ? 2 * this.lod : 1));
    gl.uniform1f(u.u_lod, coarse ? PER_CELL * this.lod ** 3 : 0);
    if (!coarse) { gl.bindVertexArray(this.pvao); this.points(); return; }
    const S = this.coarseSplats();
    gl.bindVertexArray(S.vao);
    gl.drawArrays(gl.POINTS, 0, S.count);
    gl.bindVertexArray(this.pvao);
  }

  // draw the particles (bound: pvao): the surface's when culled, else all
  points() {
    const gl = this.gl;
    if (this.cull) gl.drawElements(gl.POINTS, this.drawn, gl.UNSIGNED_INT, 0);
    else gl.drawArrays(gl.POINTS, 0, this.frame.n);
  }

  // backing-store size follows the element's CSS size × devicePixelRatio
  get pixelRatio() { return (this.software ? 1 : window.devicePixelRatio || 1) * this.scale; }

  fit() {
    const c = this.canvas, r = c.getBoundingClientRect(), dpr = this.pixelRatio;
    const w = Math.max(1, Math.round(r.width * dpr)), h = Math.max(1, Math.round(r.height * dpr));
    if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
    return [w, h];
  }

  // float render targets of the fluid passes at `fluidScale` of the output size
  ensureTargets(w, h) {
    const gl = this.gl;
    const f = Math.min(1, this.fluidScale * this.fluidFactor), fw = Math.max(1, Math.round(w * f)), fh = Math.max(1, Math.round(h * f));
    if (this.targets && this.targets.w === fw && this.targets.h === fh) return this.targets;
    if (this.targets) for (const t of this.targets.all) t();
    const all = [];
    const tex = (fmt) => {
      const t = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, t);
      gl.texStorage2D(gl.TEXTURE_2D, 1, fmt, fw, fh);
      for (const [k, v] of [[gl.TEXTURE_MIN_FILTER, gl.NEAREST], [gl.TEXTURE_MAG_FILTER, gl.NEAREST], [gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE], [gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE]]) gl.texParameteri(gl.TEXTURE_2D, k, v);
      all.push(() => gl.deleteTexture(t));
      return t;
    };
    const fbo = (t, depth) => {
      const f = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, f);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, t, 0);
      if (depth) gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
      all.push(() => gl.deleteFramebuffer(f));
      return f;
    };
    const rb = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, rb); gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, fw, fh);
    all.push(() => gl.deleteRenderbuffer(rb));
    const depthA = tex(gl.R32F), depthB = tex(gl.R32F), thick = tex(gl.R16F), shade = tex(gl.RGBA8);
    for (const t of [thick, shade]) { // these filter linearly (32-bit floats would need an extension)
      gl.bindTexture(gl.TEXTURE_2D, t);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR); gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    }
    this.targets = {
      w: fw, h: fh, all, depthA, depthB, thick, shade,
      fDepthA: fbo(depthA, rb), fDepthB: fbo(depthB, null), fThick: fbo(thick, null), fShade: fbo(shade, null),
      fSplat: fbo(depthA, rb),
    };
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.targets.fSplat);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT1, gl.TEXTURE_2D, thick, 0);
    gl.drawBuffers([gl.COLOR_ATTACHMENT0, gl.COLOR_ATTACHMENT1]);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return this.targets;
  }

  // Draw the current frame into the canvas, or into `out` = {fbo, width, height}. Returns the matrices used.
  draw(out = null) {
    const gl = this.gl, s = this.session;
    const [w, h] = out ? [out.width, out.height] : this.fit();
    const M = this.camera.matrices(w / h);
    this.last = { M, w, h };
    const dim = s ? s.dim : 2;
    gl.bindFramebuffer(gl.FRAMEBUFFER, out ? out.fbo : null);
    gl.viewport(0, 0, w, h);
    gl.depthMask(true);
    if (dim === 3) gl.clearColor(0.93, 0.945, 0.965, 1); else gl.clearColor(0.42, 0.45, 0.5, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (!s) return M;
    this.drawSolids(M, dim, false);
    const f = this.frame;
    if (f && this.showParticles) {
      const fluid = this.look === "fluid" && this.floatTargets;
      const solver = f.solver ? 1 : 0;
      if (!fluid) this.sprites(M, h, [1, 1, 1], solver, 0.62);
      else {
        if (this.hasSand || this.hasSolid) this.sprites(M, h, [0, 1, 0], solver, 0.55);
        if (this.hasWater) this.water(M, w, h, dim, solver, out);
      }
    }
    if (dim === 3) this.drawEdges(M);
    return M;
  }

  // The water's axis-aligned box projected to the screen: [x0, y0, x1, y1] pixels (y up), widened by `pad` metres; null if none
  waterRect(M, w, h, pad) {
    const { n, dim, pos } = this.frame, types = this.session.particle_type;
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let i = 0; i < n; i++) {
      if (types[i] !== WATER) continue;
      for (let d = 0; d < dim; d++) {
        const v = pos[i * dim + d];
        if (v < lo[d]) lo[d] = v;
        if (v > hi[d]) hi[d] = v;
      }
    }
    if (!(lo[0] <= hi[0])) return null;
    if (dim === 2) { lo[2] = hi[2] = 0; }
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    for (let c = 0; c < 8; c++) {
      const p = [0, 1, 2].map((d) => ((c >> d) & 1 ? hi[d] + pad : lo[d] - pad));
      const q = transform4(M.viewProj, p);
      if (q[3] <= 1e-6) return [0, 0, w, h]; // a corner behind the eye: the whole screen
      const x = ((q[0] / q[3]) * 0.5 + 0.5) * w, y = ((q[1] / q[3]) * 0.5 + 0.5) * h;
      x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y);
    }
    x0 = Math.max(0, Math.floor(x0)); y0 = Math.max(0, Math.floor(y0));
    x1 = Math.min(w, Math.ceil(x1)); y1 = Math.min(h, Math.ceil(y1));
    return x1 > x0 && y1 > y0 ? [x0, y0, x1, y1] : null;
  }

  uniforms(p, M, h) {
    const gl = this.gl, u = this.prog[p].u;
    gl.useProgram(this.prog[p].p);
    gl.uniformMatrix4fv(u.u_view, false, M.view);
    gl.uniformMatrix4fv(u.u_proj, false, M.proj);
    gl.uniform1f(u.u_pointScale, (h * M.proj[5]) / 2);
    gl.uniform1f(u.u_lod, 0);
    if (u.u_clip) { // the water's splats: clipped to the box the water rests in (3D)
      const f = this.face(), on = this.session.dim === 3;
      gl.uniform1f(u.u_clip, on ? 1 : 0);
      gl.uniformMatrix4fv(u.u_viewInv, false, on ? invert(M.view) : M.view);
      gl.uniform3fv(u.u_boxLo, [f, f, f]); gl.uniform3fv(u.u_boxHi, [1 - f, 1 - f, 1 - f]);
    }
    return u;
  }

  // Where the fluid rests against the walls [m]: (cells − 1)·dx (scenes.wall_face), one cell inside the wall band
  face() {
    const s = this.session, n = s.n_grid || (s.dim === 3 ? 64 : 128);
    return Math.max(0, (s.wall_thickness || 0) - 1 / n);
  }

  spacing() { return 1 / (2 * (this.session.n_grid || (this.session.dim === 3 ? 64 : 128))); }

  sprites(M, h, mask, solver, radiusFactor) {
    const gl = this.gl, u = this.uniforms("sprite", M, h);
    gl.uniform1f(u.u_radius, radiusFactor * this.spacing() * (this.session.dim === 3 ? 1.25 : 1.4));
    gl.uniform3fv(u.u_mask, mask);
    gl.uniform3fv(u.u_water, rgb(COLORS[WATER][solver]));
    gl.uniform3fv(u.u_sand, rgb(COLORS[SAND][solver]));
    gl.uniform3fv(u.u_wall, rgb(COLORS[WALL][0]));
    gl.uniform3fv(u.u_mud, rgb(COLORS[MUD][0]));
    gl.uniform3fv(u.u_jelly, rgb(COLORS[JELLY][0]));
    gl.uniform3fv(u.u_snow, rgb(COLORS[SNOW][0]));
    gl.uniform1f(u.u_grain, mask[0] ? 0.0 : 0.5);
    gl.uniform1f(u.u_jellyPass, 0); gl.uniform1f(u.u_alpha, 1);
    gl.enable(gl.DEPTH_TEST); gl.depthFunc(gl.LESS);
    gl.bindVertexArray(this.pvao);
    this.points();
    if (this.hasJelly && mask[1]) { // jelly last, translucent: blended over what is drawn, writing no depth
      gl.uniform1f(u.u_jellyPass, 1); gl.uniform1f(u.u_alpha, JELLY_ALPHA);
      gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA); gl.depthMask(false);
      this.points();
      gl.depthMask(true); gl.disable(gl.BLEND);
    }
  }

  water(M, w, h, dim, solver, out) {
    const gl = this.gl, T = this.ensureTargets(w, h), r = this.spacing();
    gl.bindVertexArray(this.pvao);
    gl.viewport(0, 0, T.w, T.h);
    if (dim === 3) {
      // where the water can be on the screen (its bounding box projected, with a margin): every pass is scissored to it
      const box = this.waterRect(M, w, h, 3 * r);
      if (!box) return;
      const sx = T.w / w, sy = T.h / h;
      const fbox = [Math.floor(box[0] * sx), Math.floor(box[1] * sy), Math.ceil(box[2] * sx), Math.ceil(box[3] * sy)];
      gl.enable(gl.SCISSOR_TEST);
      gl.scissor(fbox[0], fbox[1], fbox[2] - fbox[0], fbox[3] - fbox[1]);
      // 1. depth of the water's front surface and its thickness (the obstacles and the sand first: they hide the water behind them)
      const fw = this.indexed && this.onePass;
      gl.bindFramebuffer(gl.FRAMEBUFFER, fw ? T.fSplat : T.fDepthA);
      if (fw) {
        gl.clearBufferfv(gl.COLOR, 0, [1e4, 0, 0, 0]); gl.clearBufferfv(gl.COLOR, 1, [0, 0, 0, 0]); gl.clear(gl.DEPTH_BUFFER_BIT);
      } else { gl.clearColor(0, 0, 0, 0); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT); }
      gl.enable(gl.DEPTH_TEST); gl.depthFunc(gl.LESS);
      gl.colorMask(false, false, false, false);
      this.drawObstacles(M, dim);
      if (this.hasSand) this.sprites(M, T.h, [0, 1, 0], solver, 0.55);
      gl.colorMask(true, true, true, true);
      if (fw) { // one pass: MIN keeps the nearest depth, FUNC_ADD sums the thickness; the occluders' depth still tests
        const u = this.uniforms("splat", M, T.h);
        gl.uniform3fv(u.u_mask, [1, 0, 0]); gl.uniform1f(u.u_depthFrac, 1.0);
        gl.depthMask(false); gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE);
        this.indexed.blendEquationiOES(0, gl.MIN); this.indexed.blendEquationiOES(1, gl.FUNC_ADD);
        this.waterSplats(u, r);
        gl.blendEquation(gl.FUNC_ADD); gl.disable(gl.BLEND); gl.depthMask(true);
      } else {
        let u = this.uniforms("depth", M, T.h);
        gl.uniform3fv(u.u_mask, [1, 0, 0]);
        this.waterSplats(u, r);
        // 2. thickness, added up
        gl.bindFramebuffer(gl.FRAMEBUFFER, T.fThick);
        gl.clear(gl.COLOR_BUFFER_BIT);
        gl.disable(gl.DEPTH_TEST); gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE);
        u = this.uniforms("thick", M, T.h);
        gl.uniform3fv(u.u_mask, [1, 0, 0]); gl.uniform1f(u.u_kernel, 0);
        this.waterSplats(u, r);
        gl.disable(gl.BLEND);
      }
      gl.disable(gl.DEPTH_TEST);
      // 3. bilateral blur of the depth (A → B → A)
      const b = this.prog.blur;
      gl.useProgram(b.p); gl.bindVertexArray(this.emptyVao);
      const pxPerM = (T.h * M.proj[5]) / 2 / this.camera.dist;
      const rb = this.lod > 0 ? 2 * this.lod * r : r; // the splats' spacing: the bumps the blur smooths
      gl.uniform1f(b.u.u_step, Math.max(1, (pxPerM * rb) / 1.6));
      gl.uniform1f(b.u.u_falloff, 1 / (4 * rb));
      gl.uniform1i(b.u.u_taps, Math.max(1, this.blurTaps));
      gl.activeTexture(gl.TEXTURE0); gl.uniform1i(b.u.u_tex, 0);
      for (const [src, dst, dir] of this.blurTaps > 0 ? [[T.depthA, T.fDepthB, [1, 0]], [T.depthB, T.fDepthA, [0, 1]]] : []) {
        gl.bindFramebuffer(gl.FRAMEBUFFER, dst);
        gl.bindTexture(gl.TEXTURE_2D, src);
        gl.uniform2fv(b.u.u_dir, dir);
        gl.drawArrays(gl.TRIANGLES, 0, 3);
      }
      // 4. the surface shaded at this resolution (premultiplied colour and coverage)
      gl.bindFramebuffer(gl.FRAMEBUFFER, T.fShade);
      gl.clearColor(0, 0, 0, 0); gl.clear(gl.COLOR_BUFFER_BIT);
      const sp = this.prog.surface;
      gl.useProgram(sp.p);
      gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, T.depthA); gl.uniform1i(sp.u.u_depth, 0);
      gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D, T.thick); gl.uniform1i(sp.u.u_thick, 1);
      gl.uniformMatrix4fv(sp.u.u_proj, false, M.proj);
      const v = M.view; // the view's rotation is orthonormal: its inverse is its transpose
      gl.uniformMatrix3fv(sp.u.u_viewInv, false, new Float32Array([v[0], v[4], v[8], v[1], v[5], v[9], v[2], v[6], v[10]]));
      gl.uniform2f(sp.u.u_viewport, T.w, T.h);
      gl.uniform3fv(sp.u.u_water, rgb(COLORS[WATER][solver]));
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      // 5. laid over the frame, filtered up to its resolution
      gl.bindFramebuffer(gl.FRAMEBUFFER, out ? out.fbo : null);
      gl.viewport(0, 0, w, h);
      gl.scissor(box[0], box[1], box[2] - box[0], box[3] - box[1]);
      const bp = this.prog.blit;
      gl.useProgram(bp.p);
      gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, T.shade); gl.uniform1i(bp.u.u_tex, 0);
      gl.uniform2f(bp.u.u_viewport, w, h);
      gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      gl.disable(gl.BLEND); gl.disable(gl.SCISSOR_TEST);
      this.surfacesDrawn++;
      return;
    }
    // 2D: a density field of the water, thresholded and shaded (scissored to where the water is)
    const R = 3.2; // kernel radius / particle spacing: the field inside the water is about π R² / 3
    const box = this.waterRect(M, w, h, (R + 1) * r);
    if (!box) return;
    const sx = T.w / w, sy = T.h / h;
    gl.enable(gl.SCISSOR_TEST);
    gl.scissor(Math.floor(box[0] * sx), Math.floor(box[1] * sy), Math.ceil((box[2] - box[0]) * sx) + 1, Math.ceil((box[3] - box[1]) * sy) + 1);
    gl.bindFramebuffer(gl.FRAMEBUFFER, T.fThick);
    gl.clearColor(0, 0, 0, 0); gl.clear(gl.COLOR_BUFFER_BIT);
    gl.disable(gl.DEPTH_TEST); gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE);
    const u = this.uniforms("thick", M, T.h);
    gl.uniform1f(u.u_radius, R * r); gl.uniform3fv(u.u_mask, [1, 0, 0]); gl.uniform1f(u.u_kernel, 1);
    this.points();
    // shaded at this resolution (premultiplied), then laid over the frame, filtered up, behind the sand grains
    gl.bindFramebuffer(gl.FRAMEBUFFER, T.fShade);
    gl.clear(gl.COLOR_BUFFER_BIT);
    gl.disable(gl.BLEND);
    const fp = this.prog.field;
    gl.useProgram(fp.p); gl.bindVertexArray(this.emptyVao);
    gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, T.thick); gl.uniform1i(fp.u.u_thick, 0);
    gl.uniform2f(fp.u.u_viewport, T.w, T.h);
    gl.uniform3fv(fp.u.u_water, rgb(COLORS[WATER][solver]));
    gl.uniform1f(fp.u.u_level, (0.3 * Math.PI * R * R) / 3);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.bindFramebuffer(gl.FRAMEBUFFER, out ? out.fbo : null);
    gl.viewport(0, 0, w, h);
    gl.scissor(box[0], box[1], box[2] - box[0], box[3] - box[1]);
    const bp = this.prog.blit;
    gl.useProgram(bp.p);
    gl.bindTexture(gl.TEXTURE_2D, T.shade); gl.uniform1i(bp.u.u_tex, 0);
    gl.uniform2f(bp.u.u_viewport, w, h);
    gl.enable(gl.DEPTH_TEST); // at the particles' depth: sand grains stay in front
    gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.disable(gl.BLEND); gl.disable(gl.SCISSOR_TEST);
  }

  solid(mesh, M, m, color, grid = 0) {
    const gl = this.gl, p = this.prog.solid;
    gl.useProgram(p.p);
    gl.uniformMatrix4fv(p.u.u_viewProj, false, M.viewProj);
    gl.uniformMatrix4fv(p.u.u_model, false, m);
    gl.uniform3fv(p.u.u_color, color);
    gl.uniform1f(p.u.u_grid, grid);
    gl.uniform1f(p.u.u_lit, this.session.dim === 3 ? 1 : 0);
    gl.bindVertexArray(this.meshes[mesh].vao);
    gl.drawArrays(gl.TRIANGLES, 0, this.meshes[mesh].count);
  }

  drawObstacles(M, dim) {
    const gl = this.gl, col = rgb(COLORS[WALL][0]); // the legend's obstacle colour
    gl.enable(gl.CULL_FACE); gl.cullFace(gl.BACK);
    for (const ob of this.session.obstacles || []) {
      const c = dim === 3 ? ob.center : [ob.center[0], ob.center[1], -0.4]; // 2D: behind the particles
      if (ob.shape === "sphere") {
        const r = ob.radius;
        this.solid(dim === 3 ? "sphere" : "disc", M, model(c, [r, r, r]), col);
      } else {
        const e = ob.half_extents;
        this.solid(dim === 3 ? "cube" : "square", M, model(c, [e[0], e[1], e[2] || 1], rotation(ob, dim)), col);
      }
    }
    gl.disable(gl.CULL_FACE);
    if (this.bodies) this.bodies.draw(this, M, dim);
  }

  drawSolids(M, dim) {
    const gl = this.gl, t = this.face();
    gl.enable(gl.DEPTH_TEST); gl.depthFunc(gl.LESS);
    if (dim === 3) { // the room: its far walls and floor, seen from inside
      gl.enable(gl.CULL_FACE); gl.cullFace(gl.BACK);
      this.solid("room", M, model([0.5, 0.5, 0.5], [0.5 - t, 0.5 - t, 0.5 - t]), rgb("#dfe3ea"), 8);
      gl.disable(gl.CULL_FACE);
    } else { // the walls: a grey frame (the clear colour), the free region white
      gl.disable(gl.DEPTH_TEST);
      this.solid("square", M, model([0.5, 0.5, -0.5], [0.5 - t, 0.5 - t, 1]), [1, 1, 1], 0);
      gl.enable(gl.DEPTH_TEST);
    }
    this.drawObstacles(M, dim);
  }

  drawEdges(M) {
    const gl = this.gl, p = this.prog.line, t = this.face();
    gl.useProgram(p.p);
    gl.uniformMatrix4fv(p.u.u_viewProj, false, M.viewProj);
    gl.uniformMatrix4fv(p.u.u_model, false, model([0.5, 0.5, 0.5], [0.5 - t, 0.5 - t, 0.5 - t]));
    gl.uniform3fv(p.u.u_color, rgb("#7b8494"));
    gl.bindVertexArray(this.meshes.edges.vao);
    gl.drawArrays(gl.LINES, 0, this.meshes.edges.count);
  }

  // Render the frame into an offscreen RGBA8 target and read it back (top row first): [Uint8ClampedArray, w, h]
  snapshot(width, height) {
    const gl = this.gl;
    const tex = gl.createTexture(), rb = gl.createRenderbuffer(), fbo = gl.createFramebuffer();
    gl.bindTexture(gl.TEXTURE_2D, tex); gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA8, width, height);
    gl.bindRenderbuffer(gl.RENDERBUFFER, rb); gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, width, height);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, rb);
    const scaleWas = this.fluidScale;
    this.fluidScale = Math.min(1, scaleWas * (this.canvas.width / width));
    this.draw({ fbo, width, height });
    this.fluidScale = scaleWas;
    const px = new Uint8Array(width * height * 4);
    gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
    gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, px);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.deleteFramebuffer(fbo); gl.deleteRenderbuffer(rb); gl.deleteTexture(tex);
    const flipped = new Uint8ClampedArray(px.length), row = width * 4;
    for (let y = 0; y < height; y++) flipped.set(px.subarray((height - 1 - y) * row, (height - y) * row), y * row);
    return flipped;
  }

  glError() { return this.gl.getError(); }
}

// World point → CSS pixels of an element of size (cssW, cssH) under the matrices M (from draw()); null behind the eye.
export function project(M, p, cssW, cssH) {
  const c = transform4(M.viewProj, [p[0], p[1], p[2] || 0]);
  if (c[3] <= 1e-6) return null;
  return [((c[0] / c[3]) * 0.5 + 0.5) * cssW, (0.5 - (c[1] / c[3]) * 0.5) * cssH, c[3]];
}

// The ray through CSS pixel (x, y): {origin, dir} in world coordinates
export function pixelRay(M, x, y, cssW, cssH) {
  const nx = (x / cssW) * 2 - 1, ny = 1 - (y / cssH) * 2;
  const a = transform4(M.inv, [nx, ny, -1]), b = transform4(M.inv, [nx, ny, 1]);
  const p0 = [a[0] / a[3], a[1] / a[3], a[2] / a[3]], p1 = [b[0] / b[3], b[1] / b[3], b[2] / b[3]];
  const d = [p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2]], l = Math.hypot(...d) || 1;
  return { origin: p0, dir: [d[0] / l, d[1] / l, d[2] / l] };
}

// Where the ray meets the plane through `point` with normal `n` (null if parallel or behind)
export function rayPlane(ray, point, n) {
  const den = dot(ray.dir, n);
  if (Math.abs(den) < 1e-9) return null;
  const t = dot([point[0] - ray.origin[0], point[1] - ray.origin[1], point[2] - ray.origin[2]], n) / den;
  if (t < 0) return null;
  return [ray.origin[0] + t * ray.dir[0], ray.origin[1] + t * ray.dir[1], ray.origin[2] + t * ray.dir[2]];
}

// Where the ray first meets an obstacle grown by `slack` metres (a box with its rotation, a sphere): the distance
// along the ray [m], or null (a miss, only behind the origin, or a mesh: never hit). 3D; the ray's dir is a unit vector.
export function rayObstacle(ray, ob, slack = 0) {
  const o = [0, 1, 2].map((d) => ray.origin[d] - (ob.center[d] || 0)), dir = ray.dir;
  if (ob.shape === "sphere") {
    const r = ob.radius + slack, b = dot(o, dir), disc = b * b - (dot(o, o) - r * r);
    if (disc < 0) return null;
    const s = Math.sqrt(disc), t = -b - s >= 0 ? -b - s : -b + s; // from inside: where the ray leaves it
    return t >= 0 ? t : null;
  }
  if (ob.shape !== "box") return null;
  const R = rotation(ob, 3); // columns: the box's axes; the slab test in the box's frame, Rᵀ (p − centre)
  let t0 = 0, t1 = Infinity;
  for (let k = 0; k < 3; k++) {
    const ok = R[0][k] * o[0] + R[1][k] * o[1] + R[2][k] * o[2], dk = R[0][k] * dir[0] + R[1][k] * dir[1] + R[2][k] * dir[2];
    const e = (ob.half_extents[k] || 0) + slack;
    if (Math.abs(dk) < 1e-12) { if (Math.abs(ok) > e) return null; continue; }
    const a = (-e - ok) / dk, b = (e - ok) / dk;
    t0 = Math.max(t0, Math.min(a, b)); t1 = Math.min(t1, Math.max(a, b));
    if (t0 > t1) return null;
  }
  return t0;
}

// The Canvas2D fallback (no WebGL2): particles as dots, 3D scenes as their x–y view (the controller's front view).
export class Canvas2DRenderer {
  constructor(canvas) {
    this.canvas = canvas; this.ctx = canvas.getContext("2d"); this.kind = "canvas2d";
    this.look = "particles"; this.showParticles = true; this.session = null; this.frame = null; this.camera = new Camera(2);
    this.bodies = null; // the rigid bodies' layer (bodies.js)
  }
  get fluidAvailable() { return false; }
  setSession(s) { this.session = s; this.frame = null; this.camera = new Camera(2); }
  setFrame(f) { if (f.n !== this.session.num_particles) return false; this.frame = f; return true; }
  draw() {
    const c = this.canvas, ctx = this.ctx, r = c.getBoundingClientRect(), dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(r.width * dpr)), h = Math.max(1, Math.round(r.height * dpr));
    if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#ffffff"; ctx.fillRect(0, 0, r.width, r.height);
    const M = this.camera.matrices(1);
    this.last = { M, w, h };
    const s = this.session, f = this.frame;
    if (!s || !f || !this.showParticles) return M;
    const sz = Math.max(1.5, r.width / 256), types = s.particle_type, { n, dim, pos } = f;
    for (const t of [WALL, WATER, SAND, MUD, SNOW, JELLY]) {
      ctx.fillStyle = (COLORS[t] || COLORS[WATER])[f.solver ? 1 : 0];
      ctx.globalAlpha = t === JELLY ? JELLY_ALPHA : 1;
      for (let i = 0; i < n; i++) {
        if (types[i] !== t) continue;
        ctx.fillRect(pos[i * dim] * r.width - sz / 2, (1 - pos[i * dim + 1]) * r.height - sz / 2, sz, sz);
      }
    }
    ctx.globalAlpha = 1;
    if (this.bodies) this.bodies.drawCanvas(ctx, s, f, (x, y) => [x * r.width, (1 - y) * r.height]);
    return M;
  }
  snapshot(width, height) {
    const tmp = document.createElement("canvas");
    tmp.width = width; tmp.height = height;
    const ctx = tmp.getContext("2d");
    this.draw();
    ctx.drawImage(this.canvas, 0, 0, width, height);
    return ctx.getImageData(0, 0, width, height).data;
  }
  glError() { return 0; }
}
