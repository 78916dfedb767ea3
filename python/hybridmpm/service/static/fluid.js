// The "fluid" look's water, drawn by the WebGL2 renderer: 3D, screen-space fluid rendering (a depth and a
// thickness splat of the particles, a bilateral blur of the depth, shading from the normal reconstructed from
// it); 2D, a density field splatted and thresholded. GLRenderer (render.js) extends FluidPasses: these methods
// read its state (gl, prog, session, frame, the quality settings) and call its own (uniforms, points, sprites).

import { Lattice, PER_CELL, cellSplats } from "./cells.js";
import { COLORS, rgb } from "./colors.js";
import { transform4 } from "./mat.js";
import { WATER } from "/codes.js"; // the particle-type codes, served from hybridmpm.conventions

export class FluidPasses {
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

}
