// The page's colours of the particle types (the legend's), shared by the WebGL2 and Canvas2D renderers.

import { JELLY, MUD, SAND, SNOW, WALL, WATER } from "/codes.js"; // the particle-type codes, served from hybridmpm.conventions

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
export const rgb = (hex) => [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
