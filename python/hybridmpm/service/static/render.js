// The WebGL2 view of a session (hand-written, no library): the domain's walls and obstacles as solids,
// particles as shaded sprites with depth, and the "fluid" look: water as a surface (fluid.js), sand as
// grains. Its GLSL is in shaders.js, its meshes in meshes.js, the colours in colors.js; canvas2d.js is the
// fallback where WebGL2 (or a float render target) is missing, picking.js the pointer's rays.
import { Lattice, surfaceIndices } from "./cells.js";
import { COLORS, JELLY_ALPHA, rgb } from "./colors.js";
import { FluidPasses } from "./fluid.js";
import { Camera, invert } from "./mat.js";
import { BOX_EDGES, SQUARE, cube, disc, model, rotation, sphere } from "./meshes.js";
import { programs } from "./shaders.js";
import { JELLY, MUD, SAND, SNOW, WALL, WATER } from "/codes.js"; // the particle-type codes, served from hybridmpm.conventions

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
export class GLRenderer extends FluidPasses {
  constructor(canvas) {
    super();
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
    this.prog = programs(gl);
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
