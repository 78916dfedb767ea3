// The WebGL2 renderer's GLSL sources (render.js, fluid.js) and the programs built from them. The particle
// types in the shaders are the codes of /codes.js, written into the sources.

import { JELLY, MUD, SAND, SNOW, WALL, WATER } from "/codes.js"; // the particle-type codes, served from hybridmpm.conventions

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
  float on = t == ${WATER}.0 ? u_mask.x : (t == ${WALL}.0 ? u_mask.z : u_mask.y);
  if ((t == ${JELLY}.0) != (u_jellyPass > 0.5)) on = 0.0;
  vec4 vp = u_view * vec4(a_pos, 1.0);
  gl_Position = u_proj * vp;
  float r = u_radius * (t == ${SAND}.0 ? 0.78 + 0.4 * hash(a_info.y) : 1.0);
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
  vec3 base = v_type == ${WATER}.0 ? u_water : (v_type == ${SAND}.0 ? u_sand : (v_type == ${MUD}.0 ? u_mud : (v_type == ${JELLY}.0 ? u_jelly : (v_type == ${SNOW}.0 ? u_snow : u_wall))));
  if (v_type == ${SAND}.0) base *= 1.0 + u_grain * (hash(v_seed) - 0.5);
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

// The renderer's programs by name ({p, u}: the program and its uniforms' locations), compiled and linked in `gl`
export function programs(gl) {
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
  return {
    sprite: prog(SPRITE_VS, SPRITE_FS), depth: prog(SPRITE_VS, DEPTH_FS), thick: prog(SPRITE_VS, THICK_FS), splat: prog(SPRITE_VS, SPLAT_FS),
    blur: prog(QUAD_VS, BLUR_FS), surface: prog(QUAD_VS, SURFACE_FS), blit: prog(QUAD_VS, BLIT_FS), field: prog(QUAD_VS, FIELD_FS),
    solid: prog(SOLID_VS, SOLID_FS), line: prog(SOLID_VS, LINE_FS),
  };
}
