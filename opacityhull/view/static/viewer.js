// opacityhull viewer: WebGL2 EWA surfel splatting with ULR blending in the vertex shader.
// Plain ES module, no dependencies. Bundle layout: docs/viewer-format.md.
// The passes mirror opacityhull/render (renderer.render_image): per surfel the k nearest
// visible views by angle with Unstructured Lumigraph weights, sampled from a texture array
// of the views (premultiplied, bilinear); EWA kernel J V J^T + H; epsilon-z-buffer (depth
// pre-pass at z + eps, then accumulation of w*rgba, w, w*area where z <= that depth);
// resolve: colour / w, times the edge coverage clip(w*area / coverage_full, 0, 1).

const KMAX = 8;
const $ = (id) => document.getElementById(id);

// the largest canvas of aspect `aspect` (width / height) inside availW x availH CSS pixels,
// its backing store at the device pixel ratio (aspect kept to the pixel)
function fitCanvas(aspect, availW, availH, dpr) {
  const w = Math.max(1, Math.min(availW, availH * aspect));
  const width = Math.max(1, Math.round(w * dpr)), height = Math.max(1, Math.round(width / aspect));
  return { width, height, cssWidth: width / dpr, cssHeight: height / dpr };
}
const barHeight = () => { const b = $("bar"); return b ? b.getBoundingClientRect().height : 0; };

// `?` (or the ? button) shows and hides the controls; Escape hides them
function toggleHelp(show) { const h = $("help"); if (h) h.hidden = show === undefined ? !h.hidden : !show; }
document.addEventListener("keydown", (e) => {
  if (e.target && (e.target.tagName === "INPUT" || e.target.tagName === "SELECT") && e.key !== "?" && e.key !== "Escape") return;
  if (e.key === "?") { toggleHelp(); e.preventDefault(); } else if (e.key === "Escape") toggleHelp(false);
});
window.addEventListener("DOMContentLoaded", () => { const b = $("helpbutton"); if (b) b.onclick = () => toggleHelp(); });
if (document.readyState !== "loading") { const b = $("helpbutton"); if (b) b.onclick = () => toggleHelp(); }

function showError(msg) {
  const e = $("error");
  e.textContent = msg;
  e.style.display = "block";
  $("progress").textContent = "failed";
  window.opacityhull.error = msg;
  console.error(msg);
}

// fetch(url), turning a network failure or an HTTP error into a message naming what was
// being loaded and what to do about it.
async function fetchOk(url, what) {
  let r;
  try {
    r = await fetch(url);
  } catch (err) {
    throw new Error(`Could not load ${what} (${url}): ${err.message}. Is the viewer's server still running?`);
  }
  if (!r.ok) {
    throw new Error(`Could not load ${what} (${url}): HTTP ${r.status} ${r.statusText}. ` +
      `The bundle is incomplete; write it again with "opacityhull view MODEL --out DIR".`);
  }
  return r;
}

async function fetchBytes(url, expected, what) {
  const r = await fetchOk(url, what);
  const buf = await r.arrayBuffer();
  if (expected !== undefined && buf.byteLength !== expected) {
    throw new Error(`${what} (${url}) has ${buf.byteLength} bytes, expected ${expected}: the file is truncated or ` +
      `from another bundle; write the bundle again.`);
  }
  return buf;
}

// Streams url through DecompressionStream("deflate") (zlib), handing each inflated piece to
// onChunk as it arrives: the octree code is decoded level by level while it downloads.
async function fetchInflate(url, expected, what, onChunk) {
  const r = await fetchOk(url, what);
  let n = 0;
  const count = new TransformStream({ transform(chunk, ctl) { n += chunk.byteLength; ctl.enqueue(chunk); } });
  const reader = r.body.pipeThrough(count).pipeThrough(new DecompressionStream("deflate")).getReader();
  try {
    for (;;) { const { done, value } = await reader.read(); if (done) break; onChunk(value); }
  } catch (err) {
    if (err.bundleError) throw err;
    throw new Error(`${what} (${url}) could not be inflated (${err.message}): the file is truncated or corrupt; write the bundle again.`);
  }
  if (expected !== undefined && n !== expected) {
    throw new Error(`${what} (${url}) has ${n} bytes, expected ${expected}: the file is truncated or from another bundle; write the bundle again.`);
  }
}

// Statistical point geometry records (format 3; opacityhull/render/spg.py, reference
// opacityhull/view/bundle.read_bundle): inner nodes are 17-byte PCA records, leaves 8-byte
// records; both expand to the GPU layout (normal, radius, area, r_min, r_max, visibility
// words) and inner nodes to a radius tensor R² = 4 s (I - m mᵀ) C (I - m mᵀ) as well.
function tangentBasis(z) {  // Duff et al. 2017, as spg.tangent_basis
  const s = z[2] >= 0 ? 1 : -1, a = -1 / (s + z[2]), b = z[0] * z[1] * a;
  return [[1 + s * z[0] * z[0] * a, s * b, -s * z[0]], [b, s + z[1] * z[1] * a, -z[1]]];
}
function octDecode(u, v, bits) {  // as spg.oct_decode
  const q = 2 ** bits - 1;
  let x = u / q * 2 - 1, y = v / q * 2 - 1;
  const z = 1 - Math.abs(x) - Math.abs(y), t = Math.max(-z, 0);
  x -= x >= 0 ? t : -t; y -= y >= 0 ? t : -t;
  const l = Math.hypot(x, y, z);
  return [x / l, y / l, z / l];
}
function angleAxis(code, z) {  // as spg._angle_axis
  const [bx, by] = tangentBasis(z), p = code / 256 * Math.PI, c = Math.cos(p), s = Math.sin(p);
  return [c * bx[0] + s * by[0], c * bx[1] + s * by[1], c * bx[2] + s * by[2]];
}
const cross3 = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
function logValue(k, lo, hi, levels) {  // as spg._log_values
  if (k === 0) return 0;
  if (k === levels + 2) return Infinity;
  return lo * Math.max(hi / lo, 1 + 1e-12) ** ((k - 1) / levels);
}
class SpgTables {
  constructor(man, cbBuf, visBuf) {
    const S = man.spg, kp = S.codebooks.sigma_p, kn = S.codebooks.sigma_n;
    if (cbBuf.byteLength !== 4 * (3 * kp + 2 * kn)) throw new Error(`${S.codebooks.file}: ${cbBuf.byteLength} bytes, expected ${4 * (3 * kp + 2 * kn)}; write the bundle again.`);
    this.S = S; this.words = man.vis_words;
    this.cp = new Float32Array(cbBuf, 0, 3 * kp); this.cn = new Float32Array(cbBuf, 12 * kp, 2 * kn);
    this.vis = new Uint32Array(visBuf);
    this.nPatterns = this.vis.length / man.vis_words;
  }
  _vis(rec, ri, idx, what) {
    if (idx >= this.nPatterns) throw new Error(`${what}: visibility index ${idx} beyond the ${this.nPatterns} patterns; write the bundle again.`);
    const w = this.words, o = ri + 7;  // words after nrm(3) radius area r_min r_max
    for (let j = 0; j < w; j++) rec.u[o + j] = this.vis[idx * w + j];
  }
  // n inner records (17 bytes) -> {pos: Float32Array 3n, rec: {f, u} views of n GPU records, cov: Float32Array 6n}
  decodeNodes(buf, n, recBytes, what) {
    const S = this.S, b = new Uint8Array(buf), dv = new DataView(buf);
    if (b.length !== 17 * n) throw new Error(`${what}: ${b.length} bytes, expected ${17 * n}; write the bundle again.`);
    const pos = new Float32Array(3 * n), cov = new Float32Array(6 * n), ab = new ArrayBuffer(n * recBytes);
    const rec = { f: new Float32Array(ab), u: new Uint32Array(ab) }, stride = recBytes / 4;
    const [elo, ehi] = S.error_range, L = S.error_levels, sc = S.node_scale;
    for (let i = 0; i < n; i++) {
      const o = 17 * i, ri = stride * i;
      const q = dv.getUint32(o, true);
      const shifts = [0, 11, 22];
      for (let a = 0; a < 3; a++) {
        const ax = S.mean_axes[a], bits = S.mean_bits[a], m = 2 ** bits - 1;
        pos[3 * i + ax] = S.box_min[ax] + ((q >>> shifts[a]) & m) / m * S.box_size[ax];
      }
      const zp = octDecode(b[o + 4], b[o + 5], 8), xp = angleAxis(b[o + 6], zp), yp = cross3(zp, xp);
      const zn = octDecode(b[o + 7], b[o + 8], 8);
      const packed = b[o + 10] | (b[o + 11] << 8) | (b[o + 12] << 16);
      const ip = packed & 4095;
      if (ip >= this.cp.length / 3 || (packed >>> 12) >= this.cn.length / 2) throw new Error(`${what}: codebook index beyond the codebooks; write the bundle again.`);
      const sg = [Math.exp(this.cp[3 * ip]), Math.exp(this.cp[3 * ip + 1]), Math.exp(this.cp[3 * ip + 2])];
      // C = Σ σ_k² f_k f_kᵀ, projected onto the plane of the mean normal m: P C P, P = I - m mᵀ
      const F = [xp, yp, zp], C = [0, 0, 0, 0, 0, 0, 0, 0, 0];
      for (let k = 0; k < 3; k++) for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) C[3 * r + c] += sg[k] * sg[k] * F[k][r] * F[k][c];
      const m = zn, Pm = [1 - m[0] * m[0], -m[0] * m[1], -m[0] * m[2], -m[1] * m[0], 1 - m[1] * m[1], -m[1] * m[2], -m[2] * m[0], -m[2] * m[1], 1 - m[2] * m[2]];
      const T = [0, 0, 0, 0, 0, 0, 0, 0, 0], R = [0, 0, 0, 0, 0, 0, 0, 0, 0];
      for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) { let x = 0; for (let k = 0; k < 3; k++) x += Pm[3 * r + k] * C[3 * k + c]; T[3 * r + c] = x; }
      for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) { let x = 0; for (let k = 0; k < 3; k++) x += T[3 * r + k] * Pm[3 * k + c]; R[3 * r + c] = x; }
      const g = 4 * sc;
      cov.set([g * R[0], g * R[1], g * R[2], g * R[4], g * R[5], g * R[8]], 6 * i);
      // coverage area: the ellipse's, π (2σ₁)(2σ₂) of the projected covariance (det in the tangent basis)
      const [t1, t2] = tangentBasis(m);
      const q11 = quad(R, t1, t1), q12 = quad(R, t1, t2), q22 = quad(R, t2, t2);
      const area = 4 * Math.PI * Math.sqrt(Math.max(q11 * q22 - q12 * q12, 0));
      rec.f.set(m, ri);
      rec.f[ri + 3] = Math.sqrt(S.kappa * area / Math.PI);
      rec.f[ri + 4] = area;
      rec.f[ri + 5] = logValue(b[o + 13], elo, ehi, L);
      rec.f[ri + 6] = logValue(b[o + 14], elo, ehi, L);
      this._vis(rec, ri, dv.getUint16(o + 15, true), what);
    }
    return { pos, rec, cov };
  }
  // n leaf records (8 bytes) -> GPU records (positions come from the octree code)
  decodeLeaves(buf, n, recBytes, what) {
    const S = this.S, b = new Uint8Array(buf), dv = new DataView(buf);
    if (b.length !== 8 * n) throw new Error(`${what}: ${b.length} bytes, expected ${8 * n}; write the bundle again.`);
    const ab = new ArrayBuffer(n * recBytes), rec = { f: new Float32Array(ab), u: new Uint32Array(ab) }, stride = recBytes / 4;
    const [elo, ehi] = S.error_range, L = S.error_levels;
    for (let i = 0; i < n; i++) {
      const o = 8 * i, ri = stride * i, w = b[o] | (b[o + 1] << 8) | (b[o + 2] << 16);
      rec.f.set(octDecode(w & 4095, w >>> 12, 12), ri);
      rec.f[ri + 3] = logValue(b[o + 3], S.radius_range[0], S.radius_range[1], 254);
      rec.f[ri + 4] = logValue(b[o + 4], S.area_range[0], S.area_range[1], 254);
      rec.f[ri + 5] = 0;
      rec.f[ri + 6] = logValue(b[o + 5], elo, ehi, L);
      this._vis(rec, ri, dv.getUint16(o + 6, true), what);
    }
    return rec;
  }
}
function quad(R, a, b) { let x = 0; for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) x += a[r] * R[3 * r + c] * b[c]; return x; }

// Octree position code (Botsch, Wiratanaya & Kobbelt 2002), decoded breadth-first as bytes
// arrive: level l needs one byte code per occupied cell of level l-1; bit c of a code marks
// child octant c = x + 2y + 4z. After `depth` levels the occupied leaf cells are the points
// (cell centres, in Morton order), each repeated by its count. Mirrors
// opacityhull/view/octree_code.decode_positions.
class OctreeDecoder {
  constructor(head, what, onLevel) {
    this.h = head; this.what = what; this.onLevel = onLevel || (() => {});
    this.cells = new Int32Array(3);  // the root cell (0, 0, 0)
    this.level = 0; this.buf = new Uint8Array(0); this.used = 0; this.total = 0;
    this.levels = [1];
  }
  fail(msg) { const e = new Error(`${this.what}: ${msg}; write the bundle again.`); e.bundleError = true; throw e; }
  push(bytes) {
    this.total += bytes.length;
    const rest = this.buf.subarray(this.used);
    const b = new Uint8Array(rest.length + bytes.length);
    b.set(rest); b.set(bytes, rest.length);
    this.buf = b; this.used = 0;
    while (this.level < this.h.depth && this.buf.length - this.used >= this.cells.length / 3) this._expand();
    if (this.level === this.h.depth && this.buf.length > this.used) this.fail(`${this.total - this.h.n_codes} byte codes too many`);
  }
  _expand() {
    const n = this.cells.length / 3, codes = this.buf.subarray(this.used, this.used + n);
    let m = 0;
    for (let i = 0; i < n; i++) {
      let c = codes[i];
      if (c === 0) this.fail(`zero byte code at level ${this.level}`);
      while (c) { m += c & 1; c >>= 1; }
    }
    const out = new Int32Array(3 * m), cur = this.cells;
    let j = 0;
    for (let i = 0; i < n; i++) {
      const c = codes[i], x = 2 * cur[3 * i], y = 2 * cur[3 * i + 1], z = 2 * cur[3 * i + 2];
      for (let o = 0; o < 8; o++) if ((c >> o) & 1) { out[j++] = x + (o & 1); out[j++] = y + ((o >> 1) & 1); out[j++] = z + ((o >> 2) & 1); }
    }
    this.used += n; this.cells = out; this.level++;
    this.levels.push(m);
    this.onLevel(this.level, m);
  }
  // counts: Uint8Array per leaf cell, or null (one point per cell). off: null, or Botsch's
  // offset attributes {q: Uint8Array bin per point, nrm: Float32Array, stride (floats per
  // record, normal first), bits}: the centre moves (q + 0.5) * step - sqrt(3)/2 cell edges
  // along the unit normal (as octree_code.apply_offsets)
  finish(counts, off) {
    if (this.level < this.h.depth) this.fail(`the code stream ends at level ${this.level} of ${this.h.depth}`);
    const L = this.cells.length / 3;
    if (L !== this.h.n_cells) this.fail(`${L} leaf cells, the manifest says ${this.h.n_cells}`);
    const hs = this.h.size / 2 ** this.h.depth, o = this.h.origin;
    const n = this.h.n_points, P = new Float32Array(3 * n);
    if (counts && counts.length !== L) this.fail(`${counts.length} counts for ${L} leaf cells`);
    if (off && off.q.length !== n) this.fail(`${off.q.length} normal offsets for ${n} points`);
    const R = Math.sqrt(3) / 2, step = off ? 2 * R / 2 ** off.bits : 0;
    let j = 0;
    for (let i = 0; i < L; i++) {
      const k = counts ? counts[i] : 1;
      if (j + k > n) this.fail(`the counts hold more than ${n} points`);
      const x = o[0] + (this.cells[3 * i] + 0.5) * hs, y = o[1] + (this.cells[3 * i + 1] + 0.5) * hs, z = o[2] + (this.cells[3 * i + 2] + 0.5) * hs;
      for (let r = 0; r < k; r++) {
        let ox = 0, oy = 0, oz = 0;
        if (off) {
          const b = j * off.stride, nx = off.nrm[b], ny = off.nrm[b + 1], nz = off.nrm[b + 2];
          const nn = Math.hypot(nx, ny, nz);
          if (off.q[j] >= 2 ** off.bits) this.fail(`normal offset bin ${off.q[j]} out of range`);
          if (nn > 1e-12) { const d = ((off.q[j] + 0.5) * step - R) * hs / nn; ox = d * nx; oy = d * ny; oz = d * nz; }
        }
        P[3 * j] = x + ox; P[3 * j + 1] = y + oy; P[3 * j + 2] = z + oz; j++;
      }
    }
    if (j !== n) this.fail(`${j} points decoded, the manifest says ${n}`);
    return P;
  }
}

const VS = (words, shade) => `#version 300 es
precision highp float; precision highp int; precision highp sampler2D; precision highp sampler2DArray;
#define KMAX ${KMAX}
${shade ? "#define SHADE 1" : ""}
in vec3 a_pos; in vec3 a_nrm; in float a_radius; in float a_area; in float a_rmin; in float a_rmax;
in vec3 a_cov0; in vec3 a_cov1;  // radius tensor xx xy xz, yy yz zz (statistical nodes; zero: a disc)
in uvec4 a_vis0;
${words > 4 ? "in uvec4 a_vis1;" : ""}
uniform mat3 u_R; uniform vec3 u_t; uniform vec4 u_K; uniform vec2 u_size; uniform vec3 u_C;
uniform float u_sigma; uniform float u_filter; uniform float u_cutoff; uniform float u_eps; uniform float u_density;
uniform float u_mfloor; uniform float u_zdevf; uniform float u_tau;
uniform int u_nviews; uniform int u_k;
uniform sampler2D u_viewdata; uniform sampler2DArray u_views; uniform vec2 u_layer;
flat out vec2 v_c; flat out vec3 v_conic; flat out float v_w; flat out vec2 v_dz; flat out vec3 v_z;
flat out vec4 v_rgba; flat out float v_area;

bool visible(int v) {
  ${words > 4 ? "uvec4 vis = v < 128 ? a_vis0 : a_vis1;" : "uvec4 vis = a_vis0;"}
  uint w = vis[(v >> 5) & 3];
  return ((w >> uint(v & 31)) & 1u) == 1u;
}
bool before(float sa, int ra, float sb, int rb) { return sa < sb || (sa == sb && ra < rb); }
vec4 vd(int v, int j) { return texelFetch(u_viewdata, ivec2(j, v), 0); }

// world point -> pixel (u, y) of view v (OpenCV pinhole + 5-term distortion); x = nan-ish (-1e9) behind
vec2 projectView(int v, vec3 p) {
  vec4 r0 = vd(v, 0), r1 = vd(v, 1), r2 = vd(v, 2), k = vd(v, 3), d = vd(v, 4), e = vd(v, 5);
  float X = dot(r0.xyz, p) + r0.w, Y = dot(r1.xyz, p) + r1.w, Z = dot(r2.xyz, p) + r2.w;
  if (!(Z > 0.0)) return vec2(-1e9);
  float xn = X / Z, yn = Y / Z;
  float k1 = d.x, k2 = d.y, p1 = d.z, p2 = d.w, k3 = e.x;
  if (k1 != 0.0 || k2 != 0.0 || p1 != 0.0 || p2 != 0.0 || k3 != 0.0) {
    float r2_ = xn * xn + yn * yn;
    float radial = 1.0 + r2_ * (k1 + r2_ * (k2 + r2_ * k3));
    float xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2_ + 2.0 * xn * xn);
    float yd = yn * radial + p1 * (r2_ + 2.0 * yn * yn) + 2.0 * p2 * xn * yn;
    xn = xd; yn = yd;
  }
  return vec2(k.x * xn + k.z, k.y * yn + k.w);
}

void reject() { gl_Position = vec4(2.0, 2.0, 2.0, 1.0); gl_PointSize = 0.0; }

void main() {
  vec3 p = a_pos;
  // level of detail: the sequential point tree's cut, r_min <= tau * distance < r_max
  float tcut = u_tau * length(p - u_C);
  if (!(a_rmin <= tcut && tcut < a_rmax)) { reject(); return; }
  float r = a_radius * sqrt(u_density);
  v_area = a_area * u_density;
  v_rgba = vec4(0.0);
  // back faces culled in the world frame (as splat_setup)
  vec3 nw = a_nrm;
  float nn2 = dot(nw, nw);
  bool hasN = nn2 > 1e-24;
  if (!(r > 0.0) || (hasN && dot(nw, p - u_C) >= 0.0)) { reject(); return; }
  vec3 Pc = u_R * p + u_t;
  float X = Pc.x, Y = Pc.y, Z = Pc.z;
  if (!(Z > 1e-9)) { reject(); return; }
  vec3 n = hasN ? (u_R * nw) * inversesqrt(nn2) : -normalize(Pc);
  float ndp = dot(n, Pc);
  if (ndp >= 0.0) { reject(); return; }
  float fx = u_K.x, fy = u_K.y, cx = u_K.z, cy = u_K.w;
  float iz = 1.0 / Z;
  float a0 = fx * iz, a2 = -fx * X * iz * iz, b1 = fy * iz, b2 = -fy * Y * iz * iz;
  float pn0 = a0 * n.x + a2 * n.z, pn1 = b1 * n.y + b2 * n.z;
  float j00 = a0 * a0 + a2 * a2 - pn0 * pn0;
  float j01 = a2 * b2 - pn0 * pn1;
  float j11 = b1 * b1 + b2 * b2 - pn1 * pn1;
  // |J| = |(p_a x p_b) . n| (Cauchy-Binet): the CPU's sqrt(j00 j11 - j01^2) cancels badly in float32 near edge-on
  float detj = abs(-a2 * b1 * n.x - a0 * b2 * n.y + a0 * b1 * n.z);
  float s2 = (u_sigma * r) * (u_sigma * r);
  if (a_cov0.x + a_cov1.x > 0.0) {  // anisotropic: P R² Pᵀ with R² in the camera frame (as kernels.splat_setup)
    mat3 Rw = mat3(a_cov0.x, a_cov0.y, a_cov0.z, a_cov0.y, a_cov1.x, a_cov1.y, a_cov0.z, a_cov1.y, a_cov1.z);
    mat3 Rc = u_R * Rw * transpose(u_R);
    vec3 p0 = vec3(a0, 0.0, a2), p1 = vec3(0.0, b1, b2);
    j00 = dot(p0, Rc * p0); j01 = dot(p1, Rc * p0); j11 = dot(p1, Rc * p1);
    s2 = u_sigma * u_sigma;
  }
  float m00 = s2 * j00 + u_filter + u_mfloor, m01 = s2 * j01, m11 = s2 * j11 + u_filter + u_mfloor;
  float detm = m00 * m11 - m01 * m01;
  if (!(detm > 0.0)) { reject(); return; }
  float x0 = fx * X * iz + cx, y0 = fy * Y * iz + cy;
  float hx = u_cutoff * sqrt(m00), hy = u_cutoff * sqrt(m11);
  if (x0 + hx < 0.0 || x0 - hx > u_size.x - 1.0 || y0 + hy < 0.0 || y0 - hy > u_size.y - 1.0) { reject(); return; }
  float dzx = 0.0, dzy = 0.0;
  if (abs(ndp) > 1e-12 * Z) { float g = -Z * Z / ndp; dzx = g * n.x / fx; dzy = g * n.y / fy; }
  float idet = 1.0 / detm;
  v_conic = vec3(m11 * idet, -m01 * idet, m00 * idet);
  v_w = detj * sqrt(idet) / 6.283185307179586;
  v_dz = vec2(dzx, dzy);
  float lmax = 0.5 * (m00 + m11) + sqrt(0.25 * (m00 - m11) * (m00 - m11) + m01 * m01);
  float foot = u_cutoff * sqrt(lmax) * Z * 2.0 / (fx + fy);
  v_z = vec3(Z, u_zdevf * foot, u_eps * foot);
  v_c = vec2(x0, y0);

#ifndef SHADE
  // depth pass: drawn iff some view sees the surfel (the bits are set only where it projects
  // inside the view), as the accumulation pass will find at least one view then
  ${words > 4 ? "if (all(equal(a_vis0, uvec4(0u))) && all(equal(a_vis1, uvec4(0u)))) { reject(); return; }" : "if (all(equal(a_vis0, uvec4(0u)))) { reject(); return; }"}
#else
  // ULR: the k nearest views (by angle) that see the surfel and in which it projects
  vec3 dd = u_C - p;
  float nd = length(dd);
  if (!(nd > 0.0)) { reject(); return; }
  dd /= nd;
  float bs[KMAX]; int bv[KMAX]; int br[KMAX]; vec2 buv[KMAX];
  int m = 0;
  int k = u_k;
  for (int v = 0; v < u_nviews; v++) {
    if (!visible(v)) continue;
    vec4 c6 = vd(v, 6), e = vd(v, 5);
    vec3 ev = c6.xyz - p;
    float ne = length(ev);
    if (!(ne > 0.0)) continue;
    ev = ev / ne - dd;
    float s = 0.5 * dot(ev, ev);
    int rv = int(e.w);
    if (m == k && !before(s, rv, bs[k - 1], br[k - 1])) continue;
    vec2 uv = projectView(v, p);
    if (!(uv.x >= -0.5 && uv.x <= e.y - 0.5 && uv.y >= -0.5 && uv.y <= e.z - 0.5)) continue;
    int pos = m < k ? m : k - 1;
    while (pos > 0 && before(s, rv, bs[pos - 1], br[pos - 1])) {
      bs[pos] = bs[pos - 1]; bv[pos] = bv[pos - 1]; br[pos] = br[pos - 1]; buv[pos] = buv[pos - 1];
      pos--;
    }
    bs[pos] = s; bv[pos] = v; br[pos] = rv; buv[pos] = uv;
    if (m < k) m++;
  }
  if (m == 0) { reject(); return; }
  // weights: as kernels._weights (one-hot threshold raised for float32 rounding)
  float w[KMAX];
  for (int i = 0; i < KMAX; i++) w[i] = 0.0;
  if (bs[0] <= 1e-11) {
    int c = 0;
    for (int i = 0; i < m; i++) if (bs[i] <= 1e-11) c++;
    for (int i = 0; i < c; i++) w[i] = 1.0 / float(c);
  } else if (k == 1 || m == 1) {
    w[0] = 1.0;
  } else {
    float thr; int nb;
    if (m >= k) { thr = bs[k - 1]; nb = k - 1; } else { thr = 2.0; nb = m; }
    float tot = 0.0;
    for (int i = 0; i < nb; i++) { float ri = max((thr - bs[i]) / bs[i], 0.0); w[i] = ri; tot += ri; }
    if (tot > 0.0 && tot < 1e30) { for (int i = 0; i < nb; i++) w[i] /= tot; }
    else { for (int i = 0; i < m; i++) w[i] = 1.0 / float(m); }
  }
  vec4 acc = vec4(0.0);
  for (int i = 0; i < m; i++) {
    if (w[i] > 0.0) {
      vec2 uv = buv[i];
      acc += w[i] * textureLod(u_views, vec3((uv.x + 0.5) / u_layer.x, (uv.y + 0.5) / u_layer.y, float(bv[i])), 0.0);
    }
  }
  v_rgba = acc;
#endif
  gl_Position = vec4((x0 + 0.5) / u_size.x * 2.0 - 1.0, 1.0 - (y0 + 0.5) / u_size.y * 2.0, 0.0, 1.0);
  gl_PointSize = 2.0 * ceil(max(hx, hy)) + 3.0;
}`;

const FS = (shade) => `#version 300 es
precision highp float;
uniform vec2 u_size; uniform float u_cutoff; uniform float u_zscale;
flat in vec2 v_c; flat in vec3 v_conic; flat in float v_w; flat in vec2 v_dz; flat in vec3 v_z;
flat in vec4 v_rgba; flat in float v_area;
layout(location = 0) out vec4 o0;
${shade ? "layout(location = 1) out vec4 o1;" : ""}
void main() {
  vec2 px = vec2(gl_FragCoord.x - 0.5, u_size.y - gl_FragCoord.y - 0.5);
  vec2 d = px - v_c;
  float q = (v_conic.x * d.x + 2.0 * v_conic.y * d.y) * d.x + v_conic.z * d.y * d.y;
  if (q > u_cutoff * u_cutoff) discard;
  float z = clamp(v_z.x + v_dz.x * d.x + v_dz.y * d.y, v_z.x - v_z.y, v_z.x + v_z.y);
${shade ? `  gl_FragDepth = z * u_zscale;
  float w = v_w * exp(-0.5 * q);
  o0 = w * v_rgba;
  o1 = vec4(w, w * v_area, 0.0, 0.0);` : `  gl_FragDepth = (z + v_z.z) * u_zscale;
  o0 = vec4(0.0);`}
}`;

const RESOLVE_VS = `#version 300 es
void main() { vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2)); gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0); }`;

const RESOLVE_FS = `#version 300 es
precision highp float;
uniform highp sampler2D u_acc0; uniform highp sampler2D u_acc1;
uniform float u_covfull; uniform float u_amin; uniform vec3 u_bg; uniform float u_exposure;
uniform int u_useEnv; uniform highp sampler2D u_env; uniform mat3 u_Rwc; uniform vec4 u_K; uniform float u_H;
uniform float u_yaw; uniform int u_splats;
out vec4 o;
vec3 srgbDecode(vec3 c) { return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(0.04045, c)); }
// equirectangular lookup as render/background.py: u = atan2(x, -z) / 2pi, v = acos(y) / pi,
// bilinear, wrapping across the seam and clamping at the poles
vec3 envTexel(ivec2 ij, ivec2 sz) { return texelFetch(u_env, ivec2((ij.x % sz.x + sz.x) % sz.x, clamp(ij.y, 0, sz.y - 1)), 0).rgb; }
vec3 envLookup(vec3 d) {
  float c = cos(-u_yaw), s = sin(-u_yaw);
  d = vec3(c * d.x + s * d.z, d.y, -s * d.x + c * d.z);  // R_y(-yaw) d
  ivec2 sz = textureSize(u_env, 0);
  float u = atan(d.x, -d.z) / 6.283185307179586; u -= floor(u);
  float v = acos(clamp(d.y / length(d), -1.0, 1.0)) / 3.141592653589793;
  float x = u * float(sz.x) - 0.5, y = v * float(sz.y) - 0.5;
  float x0 = floor(x), y0 = floor(y), ax = x - x0, ay = y - y0;
  ivec2 p = ivec2(int(x0), int(y0));
  return envTexel(p, sz) * (1.0 - ax) * (1.0 - ay) + envTexel(p + ivec2(1, 0), sz) * ax * (1.0 - ay)
       + envTexel(p + ivec2(0, 1), sz) * (1.0 - ax) * ay + envTexel(p + ivec2(1, 1), sz) * ax * ay;
}
vec3 srgb(vec3 c) { c = clamp(c, 0.0, 1.0); return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c)); }
void main() {
  ivec2 ij = ivec2(gl_FragCoord.xy);
  vec4 a0 = texelFetch(u_acc0, ij, 0), a1 = texelFetch(u_acc1, ij, 0);
  vec3 bg = u_bg;
  if (u_useEnv == 1) {
    vec2 px = vec2(gl_FragCoord.x - 0.5, u_H - gl_FragCoord.y - 0.5);
    bg = envLookup(u_Rwc * vec3((px.x - u_K.z) / u_K.x, (px.y - u_K.w) / u_K.y, 1.0));
  }
  vec3 col = bg;
  if (u_splats == 1) {  // the fitted splats: premultiplied display colour, decoded as render_params does
    float a = clamp(a0.w, 0.0, 1.0);
    col = srgbDecode(clamp(a0.rgb, 0.0, 1.0)) + (1.0 - a) * bg;
  } else if (a1.x > 0.0) {
    float c = clamp(a1.y / u_covfull, 0.0, 1.0);
    float s = c / a1.x;
    float a = clamp(a0.w * s, 0.0, 1.0);
    vec3 pre = a >= u_amin ? a0.rgb * s : vec3(0.0);
    col = pre + (1.0 - a) * bg;
  }
  o = vec4(srgb(col * u_exposure), 1.0);
}`;

// Relight pass (relit models, docs/viewer-format.md "relight"): layer v of the relit
// texture array is view v under the chosen map, sum_j a_j * B_vj with a_j = scale_vj *
// sum_l w_l C_v[l, j] (computed on the CPU per view), B_vj the PCA eigen-images (signed
// bytes, cropped to the matte's box, tiled in layer v of the basis array), and the
// captured matte as alpha -- what Relighter.relight_view gives with pca_rank. The shading
// pass then samples this array with the same ULR as the captured views.
const RELIGHT_FS = `#version 300 es
precision highp float; precision highp int; precision highp sampler2DArray;
uniform highp sampler2DArray u_basis; uniform highp sampler2DArray u_views;
uniform int u_layer; uniform int u_rank; uniform int u_cols; uniform ivec2 u_tile; uniform ivec2 u_crop;
uniform vec3 u_a[${16}];
out vec4 o;
void main() {
  ivec2 p = ivec2(gl_FragCoord.xy);  // texel (x, row) of the layer = pixel (x, y) of the view
  float alpha = texelFetch(u_views, ivec3(p, u_layer), 0).a;
  ivec2 q = p - u_crop;
  vec3 c = vec3(0.0);
  if (q.x >= 0 && q.y >= 0 && q.x < u_tile.x && q.y < u_tile.y) {
    for (int j = 0; j < ${16}; j++) {
      if (j >= u_rank) break;
      ivec2 t = q + ivec2((j % u_cols) * u_tile.x, (j / u_cols) * u_tile.y);
      c += u_a[j] * texelFetch(u_basis, ivec3(t, u_layer), 0).rgb;
    }
  }
  o = vec4(max(c, vec3(0.0)), alpha);
}`;

// The fitted splats of build --optimize (manifest "splats", opacityhull/view/splats.py): one
// instanced quad per splat, in back-to-front order (a_idx), as the fitting's rasterizer
// (optimize/raster.py) draws them: screen covariance J W S W^T J^T + lowpass I of the two
// scaled tangent axes, cut at cutoff sigma, alpha = min(alpha_max, o G), fragments under
// alpha_min dropped; colour = SH of the view direction + 0.5 (display space), clamped at 0.
const SPLAT_VS = (texels, nsh) => `#version 300 es
precision highp float; precision highp int; precision highp sampler2D;
uniform highp sampler2D u_splats; uniform int u_P;
uniform mat3 u_R; uniform vec3 u_t; uniform vec4 u_K; uniform vec2 u_size; uniform vec3 u_C;
uniform float u_lowpass; uniform float u_cutoff; uniform float u_near;
in uint a_idx;
flat out vec2 v_mu; flat out vec3 v_conic; flat out vec4 v_col;
void main() {
  int i = int(a_idx);
  vec4 r[${texels}];
  for (int j = 0; j < ${texels}; j++) r[j] = texelFetch(u_splats, ivec2((i % u_P) * ${texels} + j, i / u_P), 0);
  vec3 m = r[0].xyz, ua = r[1].xyz, ub = vec3(r[1].w, r[2].xy);
  vec3 tc = u_R * m + u_t;
  gl_Position = vec4(0.0, 0.0, 2.0, 1.0);  // culled unless drawn below
  if (tc.z < u_near) return;
  float iz = 1.0 / tc.z;
  vec3 j0 = vec3(u_K.x * iz, 0.0, -u_K.x * tc.x * iz * iz), j1 = vec3(0.0, u_K.y * iz, -u_K.y * tc.y * iz * iz);
  vec3 Ta = u_R * ua, Tb = u_R * ub;
  vec2 pa = vec2(dot(j0, Ta), dot(j1, Ta)), pb = vec2(dot(j0, Tb), dot(j1, Tb));
  float a = pa.x * pa.x + pb.x * pb.x + u_lowpass, b = pa.x * pa.y + pb.x * pb.y, c = pa.y * pa.y + pb.y * pb.y + u_lowpass;
  float det = a * c - b * b;
  if (!(det > 0.0)) return;
  v_mu = vec2(u_K.x * tc.x * iz + u_K.z, u_K.y * tc.y * iz + u_K.w);
  v_conic = vec3(c / det, -b / det, a / det);
  // colour: real SH (3DGS constants and order) of the direction from the camera centre
  vec3 d = normalize(m - u_C);
  float x = d.x, y = d.y, z = d.z, xx = x * x, yy = y * y, zz = z * z;
  float Y[16];
  Y[0] = 0.28209479177387814;
  Y[1] = -0.4886025119029199 * y; Y[2] = 0.4886025119029199 * z; Y[3] = -0.4886025119029199 * x;
  Y[4] = 1.0925484305920792 * x * y; Y[5] = -1.0925484305920792 * y * z; Y[6] = 0.31539156525252005 * (2.0 * zz - xx - yy);
  Y[7] = -1.0925484305920792 * x * z; Y[8] = 0.5462742152960396 * (xx - yy);
  Y[9] = -0.5900435899266435 * y * (3.0 * xx - yy); Y[10] = 2.890611442640554 * x * y * z;
  Y[11] = -0.4570457994644658 * y * (4.0 * zz - xx - yy); Y[12] = 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
  Y[13] = -0.4570457994644658 * x * (4.0 * zz - xx - yy); Y[14] = 1.445305721320277 * z * (xx - yy);
  Y[15] = -0.5900435899266435 * x * (xx - 3.0 * yy);
  vec3 col = vec3(0.5);
  for (int j = 0; j < ${nsh}; j++) {
    for (int ch = 0; ch < 3; ch++) { int k = 10 + 3 * j + ch; col[ch] += Y[j] * r[k >> 2][k & 3]; }
  }
  v_col = vec4(max(col, vec3(0.0)), r[0].w);
  // the cutoff ellipse's box (+1 px: every pixel centre inside it gets a fragment)
  vec2 h = u_cutoff * sqrt(vec2(a, c)) + 1.0;
  vec2 corner = vec2(float(gl_VertexID & 1), float(gl_VertexID >> 1)) * 2.0 - 1.0;
  vec2 px = v_mu + corner * h;  // OpenCV pixel coordinates: (0, 0) = the top-left pixel's centre
  gl_Position = vec4((px.x + 0.5) / u_size.x * 2.0 - 1.0, 1.0 - (px.y + 0.5) / u_size.y * 2.0, 0.0, 1.0);
}`;

const SPLAT_FS = `#version 300 es
precision highp float;
uniform vec2 u_size; uniform float u_cutoff; uniform float u_amin; uniform float u_amax;
flat in vec2 v_mu; flat in vec3 v_conic; flat in vec4 v_col;
out vec4 o;
void main() {
  vec2 d = vec2(gl_FragCoord.x - 0.5, u_size.y - gl_FragCoord.y - 0.5) - v_mu;
  float q = (v_conic.x * d.x + 2.0 * v_conic.y * d.y) * d.x + v_conic.z * d.y * d.y;
  if (q > u_cutoff * u_cutoff) discard;
  float a = min(u_amax, v_col.w * exp(-0.5 * q));
  if (a < u_amin) discard;
  o = vec4(v_col.rgb * a, a);  // premultiplied: blended ONE, ONE_MINUS_SRC_ALPHA back to front
}`;

function compile(gl, vs, fs, what) {
  const mk = (type, src) => {
    const s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(`${what} shader: ${gl.getShaderInfoLog(s)}`);
    return s;
  };
  const p = gl.createProgram();
  gl.attachShader(p, mk(gl.VERTEX_SHADER, vs));
  gl.attachShader(p, mk(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(`${what} program: ${gl.getProgramInfoLog(p)}`);
  const u = {};
  const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < n; i++) { const info = gl.getActiveUniform(p, i); u[info.name] = gl.getUniformLocation(p, info.name); }
  return { p, u };
}

function lookAt(eye, target) {
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => { const l = Math.hypot(a[0], a[1], a[2]); return [a[0] / l, a[1] / l, a[2] / l]; };
  const z = norm(sub(target, eye));
  let x = cross(z, [0, 1, 0]);
  if (Math.hypot(...x) < 1e-9) x = cross(z, [0, 0, 1]);
  x = norm(x);
  const y = cross(z, x);
  return [x[0], y[0], z[0], eye[0], x[1], y[1], z[1], eye[1], x[2], y[2], z[2], eye[2], 0, 0, 0, 1];
}

class Viewer {
  constructor(canvas, manifest) {
    this.canvas = canvas;
    this.man = manifest;
    const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false, preserveDrawingBuffer: true,
      premultipliedAlpha: false });
    if (!gl) throw new Error("This browser has no WebGL2: the viewer needs it (try a current Chrome or Firefox).");
    this.gl = gl;
    if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("WebGL2 without EXT_color_buffer_float: cannot accumulate splats in float.");
    this.float32 = !!gl.getExtension("EXT_float_blend");
    const words = manifest.vis_words;
    this.words = words;
    this.depthProg = compile(gl, VS(words, false), FS(false), "depth pass");
    this.shadeProg = compile(gl, VS(words, true), FS(true), "accumulation pass");
    this.resolveProg = compile(gl, RESOLVE_VS, RESOLVE_FS, "resolve");
    this.relight = manifest.relight || null;
    this.lighting = null;  // null: the captured views; else the index of a bundled map
    this.relitReady = false;
    this.exposureOverride = null;
    if (this.relight) this.relightProg = compile(gl, RESOLVE_VS, RELIGHT_FS, "relight");
    // the fitted splats (build --optimize): drawn instead of the ULR surfels once loaded
    this.splats = manifest.splats || null;
    this.renderer = this.splats ? "fitted" : "ulr";
    this.splatsReady = false;
    if (this.splats) {
      const S = this.splats;
      this.splatProg = compile(gl, SPLAT_VS(S.texels, (S.sh_degree + 1) ** 2), SPLAT_FS, "fitted splats");
    }
    // positions (float32 x 3 per node: the float chunks' own, the leaves' from the octree code)
    // and the other attributes in a second buffer
    this.posVbo = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.posVbo);
    gl.bufferData(gl.ARRAY_BUFFER, manifest.n_nodes * 12, gl.STATIC_DRAW);
    this.vbo = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vbo);
    gl.bufferData(gl.ARRAY_BUFFER, manifest.n_nodes * manifest.record_bytes, gl.STATIC_DRAW);
    this.covVbo = gl.createBuffer();  // radius tensors (6 floats per node; zero for the leaves)
    gl.bindBuffer(gl.ARRAY_BUFFER, this.covVbo);
    gl.bufferData(gl.ARRAY_BUFFER, manifest.n_nodes * 24, gl.STATIC_DRAW);
    this.tables = null;
    this.vaos = [this.depthProg, this.shadeProg].map((pr) => this._vao(pr.p));
    this.loaded = 0;
    this.rLast = Infinity;  // r_max of the last node loaded: coarser cuts are complete
    this.budget = null;  // splats; null: the full model
    this.k = manifest.render.k;
    this.bg = manifest.background.slice();
    this.bgMode = "colour";
    this.envTex = null;
    this.envYawDeg = 0;
    this._viewData();
    this._allocViews();
    this.fb = null;
    const b = manifest.bounds;
    this.orbitState = { target: b.centre, az: 0, el: 20, dist: 4 * b.radius };
    this.cam = null;  // the camera drawn (baseCam scaled to the canvas when fitting the window)
    this.baseCam = null;
    this.fit = true;
    this.lastFrameMs = null;
  }

  _vao(prog) {
    const gl = this.gl, rec = this.man.record_bytes;
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vbo);
    const f = (name, size, off) => { const l = gl.getAttribLocation(prog, name); if (l >= 0) { gl.enableVertexAttribArray(l); gl.vertexAttribPointer(l, size, gl.FLOAT, false, name === "a_pos" ? 12 : rec, off); } };
    const u = (name, off) => { const l = gl.getAttribLocation(prog, name); if (l >= 0) { gl.enableVertexAttribArray(l); gl.vertexAttribIPointer(l, 4, gl.UNSIGNED_INT, rec, off); } };
    f("a_nrm", 3, 0); f("a_radius", 1, 12); f("a_area", 1, 16);
    f("a_rmin", 1, 20); f("a_rmax", 1, 24);
    u("a_vis0", 28); if (this.words > 4) u("a_vis1", 44);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.posVbo);
    f("a_pos", 3, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.covVbo);
    const c = (name, off) => { const l = gl.getAttribLocation(prog, name); if (l >= 0) { gl.enableVertexAttribArray(l); gl.vertexAttribPointer(l, 3, gl.FLOAT, false, 24, off); } };
    c("a_cov0", 0); c("a_cov1", 12);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vbo);
    gl.bindVertexArray(null);
    return vao;
  }

  _viewData() {
    const gl = this.gl, L = this.man.views.layers, V = L.length;
    const d = new Float32Array(7 * 4 * V);
    L.forEach((v, i) => {
      const T = v.world_from_cam;  // row-major 4x4; cam_from_world = [R^T | -R^T t]
      const R = [[T[0], T[1], T[2]], [T[4], T[5], T[6]], [T[8], T[9], T[10]]], t = [T[3], T[7], T[11]];
      const o = i * 28;
      for (let r = 0; r < 3; r++) {
        d[o + 4 * r] = R[0][r]; d[o + 4 * r + 1] = R[1][r]; d[o + 4 * r + 2] = R[2][r];
        d[o + 4 * r + 3] = -(R[0][r] * t[0] + R[1][r] * t[1] + R[2][r] * t[2]);
      }
      d.set([v.fx, v.fy, v.cx, v.cy], o + 12);
      d.set([v.dist[0], v.dist[1], v.dist[2], v.dist[3]], o + 16);
      d.set([v.dist[4], v.width, v.height, v.tie_rank], o + 20);
      d.set([v.centre[0], v.centre[1], v.centre[2], 0], o + 24);
    });
    this.viewTex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE1);
    gl.bindTexture(gl.TEXTURE_2D, this.viewTex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, 7, V, 0, gl.RGBA, gl.FLOAT, d);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
  }

  _allocViews() {  // storage first, so that the shaders can be compiled against it before the data arrives
    const gl = this.gl, v = this.man.views;
    this.viewsTex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.viewsTex);
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.SRGB8_ALPHA8, v.layer_width, v.layer_height, v.layers.length);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  }

  uploadViews(buf) {
    const gl = this.gl, v = this.man.views;
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.viewsTex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, 0, v.layer_width, v.layer_height, v.layers.length,
      gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(buf));
  }

  // one draw of a single (zero, hence culled) record: software GL compiles its shaders at the
  // first draw, which then overlaps the downloads instead of delaying the first picture
  warmup() {
    const n = this.loaded;
    this.loaded = 1;
    this.draw();
    this.loaded = n;
  }

  uploadEnvmap(buf) {
    const gl = this.gl, e = this.man.envmap;
    this.envTex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE4);
    gl.bindTexture(gl.TEXTURE_2D, this.envTex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB32F, e.width, e.height, 0, gl.RGB, gl.FLOAT, new Float32Array(buf));
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    this.envYawDeg = e.yaw_deg;
  }

  // the relighting chunks: basis (signed bytes), coefficients and per map its light
  // weights (float32) and its equirectangular image (float32 RGB)
  uploadRelight(basisBuf, coeffsBuf, maps) {
    const gl = this.gl, rl = this.relight, B = rl.basis, V = rl.views.length;
    const maxSize = gl.getParameter(gl.MAX_TEXTURE_SIZE), maxLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS);
    if (B.layer_width > maxSize || B.layer_height > maxSize || V > maxLayers) {
      throw new Error(`The relighting basis needs ${V} layers of ${B.layer_width}x${B.layer_height} texels; this browser's WebGL2 ` +
        `allows ${maxLayers} layers of at most ${maxSize}x${maxSize}. Write the bundle with a smaller --relight-rank.`);
    }
    if (rl.rank > 16) throw new Error(`manifest.json: relight rank ${rl.rank}, the viewer supports at most 16`);
    this.basisTex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE5);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.basisTex);
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.RGB8_SNORM, B.layer_width, B.layer_height, V);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texSubImage3D(gl.TEXTURE_2D_ARRAY, 0, 0, 0, 0, B.layer_width, B.layer_height, V, gl.RGB, gl.BYTE, new Int8Array(basisBuf));
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
    this.coeffs = new Float32Array(coeffsBuf);
    this.relitMaps = maps.map(({ weights, image }, n) => {
      const e = rl.envmaps[n];
      const tex = gl.createTexture();
      gl.activeTexture(gl.TEXTURE4);
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB32F, e.image.width, e.image.height, 0, gl.RGB, gl.FLOAT, new Float32Array(image));
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
      return { weights: new Float32Array(weights), tex };
    });
    const v = this.man.views;
    this.relitTex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE6);
    gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.relitTex);
    gl.texStorage3D(gl.TEXTURE_2D_ARRAY, 1, gl.RGBA16F, v.layer_width, v.layer_height, V);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D_ARRAY, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    this.relitFb = gl.createFramebuffer();
    this.relitKey = null;
    this.relitReady = true;
  }

  // (T, K, 3) weights of map n at yaw (deg): the bundled table, linear between steps
  relitWeights(n, yawDeg) {
    const rl = this.relight, S = rl.yaw_steps, T = rl.table_deg.length, K = rl.n_lights, W = this.relitMaps[n].weights;
    const x = (((yawDeg % 360) + 360) % 360) / (360 / S);
    const s0 = Math.floor(x), f = x - s0, a = (s0 % S) * T * K * 3, b = ((s0 + 1) % S) * T * K * 3;
    const out = new Float64Array(T * K * 3);
    for (let i = 0; i < out.length; i++) out[i] = (1 - f) * W[a + i] + f * W[b + i];
    return out;
  }

  // relight every view into the relit texture array (only when the map or yaw changed)
  relightViews() {
    const key = `${this.lighting} ${this.envYawDeg}`;
    if (this.relitKey === key) return;
    const gl = this.gl, rl = this.relight, B = rl.basis, K = rl.n_lights, r = rl.rank, u = this.relightProg.u;
    const w = this.relitWeights(this.lighting, this.envYawDeg);
    const v = this.man.views;
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.relitFb);
    gl.viewport(0, 0, v.layer_width, v.layer_height);
    gl.disable(gl.BLEND); gl.disable(gl.DEPTH_TEST);
    // only the crop is drawn: outside it the layer stays as allocated (zero) and the
    // shading pass never samples there (the crop holds every node's projection)
    gl.enable(gl.SCISSOR_TEST);
    gl.useProgram(this.relightProg.p);
    gl.activeTexture(gl.TEXTURE5); gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.basisTex);
    gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D_ARRAY, this.viewsTex);
    gl.uniform1i(u.u_basis, 5); gl.uniform1i(u.u_views, 0);
    gl.uniform1i(u.u_rank, r); gl.uniform1i(u.u_cols, B.cols); gl.uniform2i(u.u_tile, B.tile_width, B.tile_height);
    const a = new Float32Array(16 * 3);
    rl.views.forEach((vm, i) => {
      const wt = vm.table_index * K * 3, c0 = i * K * r;
      a.fill(0);
      for (let j = 0; j < r; j++) {
        for (let ch = 0; ch < 3; ch++) {
          let acc = 0;
          for (let l = 0; l < K; l++) acc += w[wt + 3 * l + ch] * this.coeffs[c0 + l * r + j];
          a[3 * j + ch] = acc * vm.scale[j];
        }
      }
      gl.framebufferTextureLayer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, this.relitTex, 0, i);
      gl.drawBuffers([gl.COLOR_ATTACHMENT0]);
      gl.uniform1i(u.u_layer, i); gl.uniform2i(u.u_crop, vm.crop[0], vm.crop[1]);
      gl.scissor(vm.crop[0], vm.crop[1], B.tile_width, B.tile_height);
      gl.uniform3fv(u["u_a[0]"], a);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    });
    gl.disable(gl.SCISSOR_TEST);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.relitKey = key;
  }

  // the fitted splats' records (float32, 4 * texels each) into an RGBA32F texture, u_P splats a row
  uploadSplats(buf) {
    const gl = this.gl, S = this.splats, T = S.texels, N = S.count;
    const maxSize = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    const P = Math.max(1, Math.min(1024, Math.floor(maxSize / T)));
    const rows = Math.max(1, Math.ceil(N / P));
    if (rows > maxSize) throw new Error(`${N} fitted splats need a ${P * T}x${rows} texture; this browser's WebGL2 allows ${maxSize}x${maxSize}`);
    const rec = new Float32Array(buf);
    if (rec.length !== N * 4 * T) throw new Error(`${S.file}: ${rec.length} floats, expected ${N * 4 * T}`);
    const data = new Float32Array(P * T * 4 * rows);
    data.set(rec);
    this.splatTex = gl.createTexture();
    gl.activeTexture(gl.TEXTURE7);
    gl.bindTexture(gl.TEXTURE_2D, this.splatTex);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA32F, P * T, rows, 0, gl.RGBA, gl.FLOAT, data);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
    this.splatP = P;
    this.splatMeans = new Float32Array(3 * N);
    for (let i = 0; i < N; i++) for (let c = 0; c < 3; c++) this.splatMeans[3 * i + c] = rec[4 * T * i + c];
    this.splatOrder = new Uint32Array(N);
    this.splatDepth = new Float32Array(N);
    this.splatIdx = gl.createBuffer();
    this.splatVao = gl.createVertexArray();
    gl.bindVertexArray(this.splatVao);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.splatIdx);
    gl.bufferData(gl.ARRAY_BUFFER, 4 * N, gl.DYNAMIC_DRAW);
    const l = gl.getAttribLocation(this.splatProg.p, "a_idx");
    gl.enableVertexAttribArray(l);
    gl.vertexAttribIPointer(l, 1, gl.UNSIGNED_INT, 4, 0);
    gl.vertexAttribDivisor(l, 1);
    gl.bindVertexArray(null);
    this.splatsReady = true;
  }

  // the splats in back-to-front order of their float32 view depth (ties: the higher index
  // first), i.e. the rasterizer's front-to-back (depth, index) order reversed
  _sortSplats(Rt, t) {
    const M = this.splatMeans, z = this.splatDepth, o = this.splatOrder, N = o.length;
    for (let i = 0; i < N; i++) {
      z[i] = Rt[2] * M[3 * i] + Rt[5] * M[3 * i + 1] + Rt[8] * M[3 * i + 2] + t[2];
      o[i] = i;
    }
    o.sort((a, b) => (z[b] - z[a]) || (b - a));
    return o;
  }

  _drawSplats(cam, Rt, t, C) {
    const gl = this.gl, S = this.splats, u = this.splatProg.u, W = cam.width, H = cam.height;
    const order = this._sortSplats(Rt, t);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.splatIdx);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, order);
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fb);
    gl.viewport(0, 0, W, H);
    gl.drawBuffers([gl.COLOR_ATTACHMENT0, gl.NONE]);
    gl.clearBufferfv(gl.COLOR, 0, [0, 0, 0, 0]);
    gl.disable(gl.DEPTH_TEST); gl.colorMask(true, true, true, true);
    gl.enable(gl.BLEND); gl.blendEquation(gl.FUNC_ADD);
    gl.blendFuncSeparate(gl.ONE, gl.ONE_MINUS_SRC_ALPHA, gl.ONE, gl.ONE_MINUS_SRC_ALPHA);
    gl.useProgram(this.splatProg.p);
    gl.activeTexture(gl.TEXTURE7); gl.bindTexture(gl.TEXTURE_2D, this.splatTex);
    gl.uniform1i(u.u_splats, 7); gl.uniform1i(u.u_P, this.splatP);
    gl.uniformMatrix3fv(u.u_R, false, Rt); gl.uniform3fv(u.u_t, t); gl.uniform3fv(u.u_C, C);
    gl.uniform4f(u.u_K, cam.fx, cam.fy, cam.cx, cam.cy); gl.uniform2f(u.u_size, W, H);
    gl.uniform1f(u.u_lowpass, S.lowpass_px2); gl.uniform1f(u.u_cutoff, S.cutoff_sigma); gl.uniform1f(u.u_near, S.near_m);
    gl.uniform1f(u.u_amin, S.alpha_min); gl.uniform1f(u.u_amax, S.alpha_max);
    gl.bindVertexArray(this.splatVao);
    gl.drawArraysInstanced(gl.TRIANGLE_STRIP, 0, 4, order.length);
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND);
  }

  // a chunk of packed inner nodes (17 bytes each), decoded to positions, GPU records and tensors
  uploadChunk(c, buf) {
    const gl = this.gl;
    const d = this.tables.decodeNodes(buf, c.count, this.man.record_bytes, `node chunk ${c.file}`);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.posVbo);
    gl.bufferSubData(gl.ARRAY_BUFFER, c.first * 12, d.pos);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vbo);
    gl.bufferSubData(gl.ARRAY_BUFFER, c.first * this.man.record_bytes, d.rec.f);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.covVbo);
    gl.bufferSubData(gl.ARRAY_BUFFER, c.first * 24, d.cov);
    this.loaded = Math.max(this.loaded, c.first + c.count);
    // leaves still to come have r_max <= leaves.r_max_max: cuts above it are complete
    const pending = this.man.leaves ? this.man.leaves.r_max_max : 0;
    this.rLast = this.loaded >= this.man.n_nodes ? 0 : Math.max(this.loaded >= this.man.n_float ? 0 : c.r_max_last, pending);
  }

  // the octree-coded leaves: decoded positions (Float32Array, 3 per leaf) and their decoded records
  uploadLeaves(P, rec) {
    const gl = this.gl, L = this.man.leaves;
    gl.bindBuffer(gl.ARRAY_BUFFER, this.posVbo);
    gl.bufferSubData(gl.ARRAY_BUFFER, L.first * 12, P);
    gl.bindBuffer(gl.ARRAY_BUFFER, this.vbo);
    gl.bufferSubData(gl.ARRAY_BUFFER, L.first * this.man.record_bytes, rec.f);
    this.leafPositions = P;
    this.loaded = this.man.n_nodes;
    this.rLast = 0;
  }

  _targets(W, H) {
    const gl = this.gl;
    if (this.fb && this.fbW === W && this.fbH === H) return;
    const fmt = this.float32 ? gl.RGBA32F : gl.RGBA16F;
    const mk = (ifmt, f, t) => { const x = gl.createTexture(); gl.bindTexture(gl.TEXTURE_2D, x); gl.texStorage2D(gl.TEXTURE_2D, 1, ifmt, W, H);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST); gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST); return x; };
    gl.activeTexture(gl.TEXTURE2);
    this.acc0 = mk(fmt); this.acc1 = mk(fmt); this.depth = mk(gl.DEPTH_COMPONENT32F);
    this.fb = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, this.fb);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, this.acc0, 0);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT1, gl.TEXTURE_2D, this.acc1, 0);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.TEXTURE_2D, this.depth, 0);
    const st = gl.checkFramebufferStatus(gl.FRAMEBUFFER);
    if (st !== gl.FRAMEBUFFER_COMPLETE) throw new Error(`float framebuffer incomplete (status 0x${st.toString(16)})`);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    this.fbW = W; this.fbH = H;
  }

  setCamera(cam) {  // {fx, fy, cx, cy, width, height, world_from_cam: 16 row-major}
    this.baseCam = cam;
    if (!this.fit) {  // exactly the camera's image (the API's captured cameras, tests)
      this.cam = cam;
      this.canvas.width = cam.width;
      this.canvas.height = cam.height;
      this.canvas.style.width = ""; this.canvas.style.height = "";
      return;
    }
    // fill the window below the control bar with the camera's aspect, at the device pixel
    // ratio: the same camera with its intrinsics scaled (pixel centres: OpenCV, (0, 0) = top-left centre)
    const fit = fitCanvas(cam.width / cam.height, window.innerWidth, window.innerHeight - barHeight(), window.devicePixelRatio || 1);
    const sx = fit.width / cam.width, sy = fit.height / cam.height;
    this.cam = { ...cam, fx: cam.fx * sx, fy: cam.fy * sy, cx: (cam.cx + 0.5) * sx - 0.5, cy: (cam.cy + 0.5) * sy - 0.5,
      width: fit.width, height: fit.height };
    this.canvas.width = fit.width;
    this.canvas.height = fit.height;
    this.canvas.style.width = `${fit.cssWidth}px`; this.canvas.style.height = `${fit.cssHeight}px`;
  }

  setFit(on) { this.fit = !!on; if (this.baseCam) this.setCamera(this.baseCam); }

  setView(i) {
    const v = this.man.views.layers[i];
    if (!v) throw new Error(`no captured view ${i} (the model has ${this.man.views.layers.length})`);
    this.setCamera({ fx: v.fx, fy: v.fy, cx: v.cx, cy: v.cy, width: v.width, height: v.height, world_from_cam: v.world_from_cam });
    const c = v.centre, t = this.orbitState.target;
    const d = [c[0] - t[0], c[1] - t[1], c[2] - t[2]], r = Math.hypot(...d);
    this.orbitState = { target: t, dist: r, el: Math.asin(d[1] / r) * 180 / Math.PI, az: Math.atan2(d[0], d[2]) * 180 / Math.PI };
  }

  orbit(dAz, dEl, zoom = 1) {
    const o = this.orbitState;
    o.az += dAz; o.el = Math.max(-89, Math.min(89, o.el + dEl)); o.dist *= zoom;
    const a = o.az * Math.PI / 180, e = o.el * Math.PI / 180;
    const eye = [o.target[0] + o.dist * Math.cos(e) * Math.sin(a), o.target[1] + o.dist * Math.sin(e),
      o.target[2] + o.dist * Math.cos(e) * Math.cos(a)];
    const base = this.baseCam || this._defaultIntrinsics();
    this.setCamera({ ...base, world_from_cam: lookAt(eye, o.target) });
  }

  // tau of the cut: the budget's uniform threshold t (from the manifest's table) over the
  // distance to the model, and no finer than what the loaded prefix of the tree supports
  tau(dist) {
    const b = this.man.bounds, L = this.man.lod;
    let tau = 0;
    if (this.budget !== null && this.budget < this.man.n_surfels) {
      let t = L.t[L.t.length - 1];
      for (let i = 1; i < L.t.length; i++) {
        if (L.splats[i] <= this.budget) {
          const n0 = L.splats[i - 1], n1 = L.splats[i], f = n0 > n1 ? (n0 - this.budget) / (n0 - n1) : 1;
          t = L.t[i - 1] > 0 ? Math.exp(Math.log(L.t[i - 1]) + f * (Math.log(L.t[i]) - Math.log(L.t[i - 1]))) : f * L.t[i];
          break;
        }
      }
      tau = t / Math.max(dist, 1e-9);
    }
    if (this.rLast > 0) tau = Math.max(tau, this.rLast / Math.max(dist - b.radius, 0.05 * dist, 1e-9));
    return tau;
  }

  _defaultIntrinsics() {
    const v = this.man.views.layers[0];
    return { fx: v.fx, fy: v.fy, cx: v.cx, cy: v.cy, width: v.width, height: v.height };
  }

  draw() {
    const gl = this.gl, man = this.man, cam = this.cam, r = man.render;
    const t0 = performance.now();
    const W = cam.width, H = cam.height;
    this._targets(W, H);
    const T = cam.world_from_cam;
    // cam_from_world: R^T, -R^T t; uniformMatrix3fv takes column-major, i.e. rows of R^T = columns of R... pass R^T
    const Rt = new Float32Array([T[0], T[1], T[2], T[4], T[5], T[6], T[8], T[9], T[10]]);  // column-major of R^T
    const C = [T[3], T[7], T[11]];
    const t = [-(T[0] * C[0] + T[4] * C[1] + T[8] * C[2]), -(T[1] * C[0] + T[5] * C[1] + T[9] * C[2]), -(T[2] * C[0] + T[6] * C[1] + T[10] * C[2])];
    const b = man.bounds;
    const dist = Math.hypot(C[0] - b.centre[0], C[1] - b.centre[1], C[2] - b.centre[2]);
    const zscale = 1 / (2 * (dist + 4 * b.radius) + 1e-9);
    const density = 1.0;
    const tau = this.tau(dist);
    this.lastTau = tau;  // (the CPU reference draws the same cut: bundle.bundle_cut)
    // relit (a bundled map chosen) the page blends the relit views on the hull's surfels:
    // the splats' SH holds the captured lighting only
    const fitted = this.renderer === "fitted" && this.splatsReady && this.lighting === null;
    const relit = this.lighting !== null && this.relitReady;
    if (relit) this.relightViews();
    if (fitted) this._drawSplats(cam, Rt, t, C);
    else {
      gl.bindFramebuffer(gl.FRAMEBUFFER, this.fb);
      gl.viewport(0, 0, W, H);
      gl.drawBuffers([gl.COLOR_ATTACHMENT0, gl.COLOR_ATTACHMENT1]);
      gl.clearBufferfv(gl.COLOR, 0, [0, 0, 0, 0]);
      gl.clearBufferfv(gl.COLOR, 1, [0, 0, 0, 0]);
      gl.clearBufferfv(gl.DEPTH, 0, [1]);
      gl.enable(gl.DEPTH_TEST);
      gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D_ARRAY, relit ? this.relitTex : this.viewsTex);
      gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D, this.viewTex);
      for (const [pi, prog] of [[0, this.depthProg], [1, this.shadeProg]]) {
        const u = prog.u;
        gl.useProgram(prog.p);
        gl.uniformMatrix3fv(u.u_R, false, Rt);
        gl.uniform3fv(u.u_t, t); gl.uniform4f(u.u_K, cam.fx, cam.fy, cam.cx, cam.cy); gl.uniform2f(u.u_size, W, H);
        gl.uniform3fv(u.u_C, C); gl.uniform1f(u.u_sigma, r.sigma_radius); gl.uniform1f(u.u_filter, r.filter);
        gl.uniform1f(u.u_cutoff, r.cutoff); gl.uniform1f(u.u_eps, r.epsilon_z); gl.uniform1f(u.u_density, density);
        gl.uniform1f(u.u_mfloor, r.m_floor); gl.uniform1f(u.u_zdevf, r.zdev_footprints);
        gl.uniform1i(u.u_nviews, man.n_views); gl.uniform1i(u.u_k, this.k);
        gl.uniform1i(u.u_views, 0); gl.uniform1i(u.u_viewdata, 1);
        gl.uniform2f(u.u_layer, man.views.layer_width, man.views.layer_height);
        gl.uniform1f(u.u_zscale, zscale); gl.uniform1f(u.u_tau, tau);
        gl.bindVertexArray(this.vaos[pi]);
        if (pi === 0) {
          gl.drawBuffers([gl.COLOR_ATTACHMENT0, gl.NONE]);
          gl.colorMask(false, false, false, false); gl.depthMask(true); gl.depthFunc(gl.LESS); gl.disable(gl.BLEND);
        } else {
          gl.drawBuffers([gl.COLOR_ATTACHMENT0, gl.COLOR_ATTACHMENT1]);
          gl.colorMask(true, true, true, true); gl.depthMask(false); gl.depthFunc(gl.LEQUAL);
          gl.enable(gl.BLEND); gl.blendFunc(gl.ONE, gl.ONE); gl.blendEquation(gl.FUNC_ADD);
        }
        gl.drawArrays(gl.POINTS, 0, this.loaded);
      }
    }
    gl.bindVertexArray(null);
    gl.disable(gl.BLEND); gl.disable(gl.DEPTH_TEST); gl.depthMask(true);
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, W, H);
    const rp = this.resolveProg;
    gl.useProgram(rp.p);
    gl.activeTexture(gl.TEXTURE2); gl.bindTexture(gl.TEXTURE_2D, this.acc0);
    gl.activeTexture(gl.TEXTURE3); gl.bindTexture(gl.TEXTURE_2D, this.acc1);
    gl.uniform1i(rp.u.u_acc0, 2); gl.uniform1i(rp.u.u_acc1, 3); gl.uniform1i(rp.u.u_splats, fitted ? 1 : 0);
    gl.uniform1f(rp.u.u_covfull, r.coverage_full); gl.uniform1f(rp.u.u_amin, r.alpha_min);
    gl.uniform3fv(rp.u.u_bg, this.bg);
    // the background map: the relighting map when relit, else the bundle's --envmap
    const envTex = relit ? this.relitMaps[this.lighting].tex : this.envTex;
    const useEnv = this.bgMode === "envmap" && envTex ? 1 : 0;
    gl.uniform1i(rp.u.u_useEnv, useEnv);
    gl.uniform1f(rp.u.u_exposure, this.exposureOverride !== null ? this.exposureOverride : relit ? this.relight.envmaps[this.lighting].exposure : 1.0);
    gl.activeTexture(gl.TEXTURE4); gl.bindTexture(gl.TEXTURE_2D, useEnv ? envTex : this.acc1);
    gl.uniform1i(rp.u.u_env, 4);
    // world_from_cam rotation, column-major
    gl.uniformMatrix3fv(rp.u.u_Rwc, false, new Float32Array([T[0], T[4], T[8], T[1], T[5], T[9], T[2], T[6], T[10]]));
    gl.uniform4f(rp.u.u_K, cam.fx, cam.fy, cam.cx, cam.cy); gl.uniform1f(rp.u.u_H, H);
    gl.uniform1f(rp.u.u_yaw, this.envYawDeg * Math.PI / 180);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    const px = new Uint8Array(4);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);  // waits for the frame: honest timing
    this.lastFrameMs = performance.now() - t0;
    return this.lastFrameMs;
  }
}

async function main() {
  const api = window.opacityhull;
  const progress = $("progress");
  let man;
  try {
    const r = await fetch("manifest.json");
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    man = await r.json();
  } catch (err) {
    throw new Error(`This folder is not an opacityhull viewer bundle: manifest.json could not be read (${err.message}). ` +
      `Write one with "opacityhull view MODEL --out DIR".`);
  }
  api.timings = { manifest: performance.now() };
  if (man.format !== "opacityhull-viewer/3") throw new Error(`manifest.json: format ${JSON.stringify(man.format)}, expected "opacityhull-viewer/3" (write the bundle again with this version)`);
  const viewer = new Viewer($("canvas"), man);
  api.timings.gl_setup = performance.now();
  api.viewer = viewer;
  api.manifest = man;
  const sel = $("view");
  man.views.layers.forEach((v, i) => { const o = document.createElement("option"); o.value = i; o.textContent = `${i}: ${v.id}`; sel.appendChild(o); });
  viewer.setView(0);
  const L = man.leaves, H = man.positions;
  const RL = man.relight;
  const relightBytes = RL ? RL.basis.bytes + RL.coeffs.bytes + RL.envmaps.reduce((a, e) => a + e.weights.bytes + (e.image.file === (man.envmap && man.envmap.file) ? 0 : e.image.bytes), 0) : 0;
  const S = man.spg;
  const total = (man.splats ? man.splats.bytes : 0) + man.views.bytes + S.codebooks.bytes + S.visibility.bytes + man.chunks.reduce((a, c) => a + c.bytes, 0) + (L ? L.bytes + H.codes_bytes + H.counts_bytes + H.offsets_bytes : 0) + relightBytes;
  let got = 0;
  const report = () => { progress.textContent = `loading ${(100 * got / total).toFixed(0)} % — ${viewer.loaded} / ${man.n_nodes} nodes`; };
  report();
  const bud = $("budget");
  for (const f of [1, 1 / 4, 1 / 16, 1 / 64]) {
    const o = document.createElement("option");
    o.value = f === 1 ? "" : String(Math.round(man.n_surfels * f));
    o.textContent = f === 1 ? `all ${man.n_surfels}` : `${o.value} (1/${Math.round(1 / f)})`;
    bud.appendChild(o);
  }
  const tablesP = Promise.all([fetchBytes(S.codebooks.file, S.codebooks.bytes, "the spread codebooks"),
    fetchBytes(S.visibility.file, S.visibility.bytes, "the visibility dictionary")]);
  tablesP.catch(() => {});
  const viewsP = fetchBytes(man.views.file, man.views.bytes, "the views' texture array");
  const c0 = man.chunks[0];
  const chunk0P = fetchBytes(c0.file, c0.bytes, `surfel chunk 1 of ${man.chunks.length}`);
  viewsP.catch(() => {}); chunk0P.catch(() => {});  // awaited below; no "unhandled rejection" noise
  viewer.warmup();
  api.timings.warmup = performance.now();
  if (man.splats) {  // a fitted model: its splats are the picture, so they come first
    viewer.uploadSplats(await fetchBytes(man.splats.file, man.splats.bytes, "the fitted splats"));
    got += man.splats.bytes; report();
    api.timings.splats = performance.now();
    viewer.draw();
    const rs = $("renderer");
    $("rendererlabel").style.display = "";
    rs.value = viewer.renderer;
    rs.onchange = () => { viewer.renderer = rs.value; dirty = true; };
  }
  viewer.uploadViews(await viewsP);
  got += man.views.bytes; report();
  api.timings.views = performance.now();
  let envBuf = null;  // the --envmap map, shared with the relighting maps when it is one
  if (man.envmap) {
    envBuf = await fetchBytes(man.envmap.file, man.envmap.bytes, "the environment map");
    viewer.uploadEnvmap(envBuf);
    const o = document.createElement("option"); o.value = "envmap"; o.textContent = `environment map (${man.envmap.source})`;
    $("bg").appendChild(o);
    const yaw = $("yaw"); yaw.value = man.envmap.yaw_deg; $("yawlabel").style.display = "";
    $("yawval").textContent = `${yaw.value}°`;
    yaw.oninput = () => { viewer.envYawDeg = +yaw.value; $("yawval").textContent = `${yaw.value}°`; dirty = true; };
  }
  let dirty = true;
  const frame = () => { if (dirty) { dirty = false; viewer.draw(); $("fps").textContent = `${viewer.lastFrameMs.toFixed(1)} ms/frame`; } requestAnimationFrame(frame); };
  api.redraw = () => { dirty = true; };
  const [cbBuf, visBuf] = await tablesP;
  viewer.tables = new SpgTables(man, cbBuf, visBuf);
  got += S.codebooks.bytes + S.visibility.bytes;
  for (const [ci, c] of man.chunks.entries()) {
    viewer.uploadChunk(c, ci === 0 ? await chunk0P : await fetchBytes(c.file, c.bytes, `surfel chunk ${ci + 1} of ${man.chunks.length}`));
    got += c.bytes; report();
    // the first (coarse) chunk is drawn at once; later ones through the frame loop, so that
    // downloads are not held up by frames of a half-loaded model
    if (ci === 0) {
      api.timings.chunk0 = performance.now();
      viewer.draw();
      api.firstFrameMs = performance.now();
      requestAnimationFrame(frame);
    } else dirty = true;
  }
  if (L) {  // the octree-coded leaves: positions decoded level by level while they download
    const t0 = performance.now();
    const what = `the octree position code (${H.codes_file})`;
    const dec = new OctreeDecoder(H, what, (l, m) => { progress.textContent = `positions: octree level ${l} / ${H.depth}, ${m} cells`; });
    const leavesP = fetchBytes(L.file, L.bytes, "the octree-coded leaves' records");
    leavesP.catch(() => {});
    await fetchInflate(H.codes_file, H.codes_bytes, what, (b) => dec.push(b));
    const inflateAll = async (file, bytes, what) => {
      const parts = [];
      await fetchInflate(file, bytes, what, (b) => parts.push(b));
      const out = new Uint8Array(parts.reduce((a, b) => a + b.length, 0));
      let o = 0; for (const b of parts) { out.set(b, o); o += b.length; }
      return out;
    };
    const counts = H.counts_file ? await inflateAll(H.counts_file, H.counts_bytes, `the octree cell counts (${H.counts_file})`) : null;
    const leafRec = viewer.tables.decodeLeaves(await leavesP, L.count, man.record_bytes, `the leaf records (${L.file})`);
    let off = null;
    if (H.offsets_file) {
      const q = await inflateAll(H.offsets_file, H.offsets_bytes, `the octree normal offsets (${H.offsets_file})`);
      off = { q, nrm: leafRec.f, stride: man.record_bytes / 4, bits: H.offset_bits };
    }
    const P = dec.finish(counts, off);
    api.octree = { levels: dec.levels, decode_ms: performance.now() - t0 };
    got += H.codes_bytes + H.counts_bytes + H.offsets_bytes; report();
    viewer.uploadLeaves(P, leafRec);
    got += L.bytes; report();
    api.timings.leaves = performance.now();
    dirty = true;
  }
  if (RL) {  // relighting: PCA basis, coefficients, per map its weights and image (after the geometry)
    progress.textContent = "loading the relighting data…";
    const basis = await fetchBytes(RL.basis.file, RL.basis.bytes, "the relighting PCA basis");
    const coeffs = await fetchBytes(RL.coeffs.file, RL.coeffs.bytes, "the relighting PCA coefficients");
    const maps = [];
    for (const e of RL.envmaps) {
      const weights = await fetchBytes(e.weights.file, e.weights.bytes, `the light weights of environment map ${e.name}`);
      const image = man.envmap && e.image.file === man.envmap.file ? envBuf : await fetchBytes(e.image.file, e.image.bytes, `environment map ${e.name}`);
      maps.push({ weights, image });
    }
    viewer.uploadRelight(basis, coeffs, maps);
    got += relightBytes; report();
    api.timings.relight = performance.now();
    const ls = $("light");
    RL.envmaps.forEach((e, i) => { const o = document.createElement("option"); o.value = i; o.textContent = `relit: ${e.name}`; ls.appendChild(o); });
    $("lightlabel").style.display = "";
    const yaw = $("yaw");
    yaw.min = 0; yaw.max = 360; yaw.step = 360 / RL.yaw_steps;
    $("yawlabel").style.display = ""; $("yawval").textContent = `${yaw.value}°`;
    yaw.oninput = () => { viewer.envYawDeg = +yaw.value; $("yawval").textContent = `${yaw.value}°`; dirty = true; };
    ls.onchange = () => {
      if (ls.value === "") viewer.lighting = null;
      else {
        viewer.lighting = +ls.value; viewer.envYawDeg = RL.envmaps[viewer.lighting].default_yaw_deg;
        yaw.value = viewer.envYawDeg; $("yawval").textContent = `${yaw.value}°`;
        viewer.bgMode = "envmap"; $("bg").value = "envmap";
      }
      dirty = true;
    };
    if (!man.envmap) {  // the background picker can show the relighting map
      const o = document.createElement("option"); o.value = "envmap"; o.textContent = "environment map (the relighting map)";
      $("bg").appendChild(o);
    }
  }
  progress.textContent = `${man.splats ? `${man.splats.count} fitted splats, ` : ""}${man.n_surfels} surfels, ${man.n_views} views${RL ? `, relightable (PCA rank ${RL.rank}, ${RL.n_lights} lights)` : ""}`;
  // controls
  sel.onchange = () => { viewer.fit = true; viewer.setView(+sel.value); dirty = true; };
  const kIn = $("k"); kIn.value = viewer.k; $("kval").textContent = viewer.k;
  kIn.oninput = () => { viewer.k = +kIn.value; $("kval").textContent = kIn.value; dirty = true; };
  bud.onchange = () => { viewer.budget = bud.value === "" ? null : +bud.value; dirty = true; };
  $("bg").onchange = () => {
    const v = $("bg").value;
    if (v === "envmap") viewer.bgMode = "envmap"; else { viewer.bgMode = "colour"; viewer.bg = v.split(",").map(Number); }
    dirty = true;
  };
  const bgKey = man.background.join(",");
  if (Array.from($("bg").options).some((o) => o.value === bgKey)) $("bg").value = bgKey;
  for (const b of document.querySelectorAll("#bgbuttons button")) {  // one click: grey, black, white
    b.onclick = () => { $("bg").value = b.dataset.rgb; $("bg").onchange(); };
  }
  // refit when the window or the control bar (it wraps as controls appear) changes size
  const refit = () => { if (viewer.fit && viewer.baseCam) { viewer.setCamera(viewer.baseCam); dirty = true; } };
  window.addEventListener("resize", refit);
  if (window.ResizeObserver) new ResizeObserver(refit).observe($("bar"));
  refit();
  const cv = $("canvas");
  let drag = null;
  cv.onpointerdown = (e) => { drag = [e.clientX, e.clientY]; cv.setPointerCapture(e.pointerId); };
  cv.onpointermove = (e) => { if (!drag) return; viewer.orbit(-(e.clientX - drag[0]) * 0.4, (e.clientY - drag[1]) * 0.4); drag = [e.clientX, e.clientY]; dirty = true; };
  cv.onpointerup = () => { drag = null; };
  cv.onwheel = (e) => { e.preventDefault(); viewer.orbit(0, 0, Math.exp(e.deltaY * 0.001)); dirty = true; };
  viewer.draw();
  return viewer;
}

let resolveReady, rejectReady;
window.opacityhull = {
  error: null, lastFrameMs: null, firstFrameMs: null, viewer: null,
  ready: new Promise((res, rej) => { resolveReady = res; rejectReady = rej; }),
  setCamera(i) { this.viewer.fit = false; this.viewer.setView(i); return this.viewer.draw(); },
  setCameraMatrix(cam) { this.viewer.fit = false; this.viewer.setCamera(cam); return this.viewer.draw(); },
  // fill the window (true, the page's default) or draw at the camera's own size (false)
  setFit(on) { this.viewer.setFit(on); return this.viewer.draw(); },
  // "fitted": the splats of build --optimize (bundles that have them); "ulr": the captured views blended
  setRenderer(name) {
    if (name === "fitted" && !this.viewer.splatsReady) throw new Error("this bundle has no fitted splats (the model was not built with --optimize)");
    if (name !== "fitted" && name !== "ulr") throw new Error(`renderer ${JSON.stringify(name)}: expected "fitted" or "ulr"`);
    this.viewer.renderer = name;
    const rs = document.getElementById("renderer"); if (rs) rs.value = name;
    return this.viewer.draw();
  },
  setK(k) { this.viewer.k = Math.max(1, Math.min(KMAX, k | 0)); return this.viewer.draw(); },
  setBudget(n) { this.viewer.budget = n === null || n === undefined ? null : Math.max(1, n | 0); return this.viewer.draw(); },
  setBackground(rgb) {  // [r, g, b] (linear) or "envmap"
    if (rgb === "envmap") { if (!this.viewer.envTex) throw new Error("this bundle has no environment map"); this.viewer.bgMode = "envmap"; }
    else { this.viewer.bgMode = "colour"; this.viewer.bg = rgb.slice(0, 3); }
    return this.viewer.draw();
  },
  setEnvYaw(deg) { this.viewer.envYawDeg = deg; return this.viewer.draw(); },
  // relit models: env = index or name of a bundled map (null: the captured views), yaw in
  // degrees (default: the map's default yaw); the background follows (envmap mode)
  setRelight(env, yawDeg) {
    const v = this.viewer, rl = v.relight;
    if (!rl || !v.relitReady) throw new Error("this bundle has no relighting data (the model has no reflectance)");
    if (env === null) { v.lighting = null; return v.draw(); }
    const i = typeof env === "number" ? env : rl.envmaps.findIndex((e) => e.name === env);
    if (!(i >= 0 && i < rl.envmaps.length)) throw new Error(`no bundled environment map ${JSON.stringify(env)} (have ${rl.envmaps.map((e) => e.name).join(", ")})`);
    v.lighting = i;
    v.envYawDeg = yawDeg === undefined || yawDeg === null ? rl.envmaps[i].default_yaw_deg : +yawDeg;
    v.bgMode = "envmap";
    return v.draw();
  },
  setExposure(x) { this.viewer.exposureOverride = x === null || x === undefined ? null : +x; return this.viewer.draw(); },
  orbit(dAz, dEl, zoom = 1) { this.viewer.orbit(dAz, dEl, zoom); return this.viewer.draw(); },
  // the leaves' positions as decoded from the octree code (flat x y z list, float32 values)
  leafPositions() { const P = this.viewer.leafPositions; return P ? Array.from(P) : null; },
  // the float accumulators of the last frame, rows top to bottom: [att0 (w*rgba), att1 (w, w*area, 0, 0)]
  accumulators() {
    const v = this.viewer, gl = v.gl, W = v.fbW, H = v.fbH, out = [];
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, v.fb);
    for (const att of [gl.COLOR_ATTACHMENT0, gl.COLOR_ATTACHMENT1]) {
      gl.readBuffer(att);
      const px = new Float32Array(W * H * 4);
      gl.readPixels(0, 0, W, H, gl.RGBA, gl.FLOAT, px);
      const rows = [];
      for (let y = H - 1; y >= 0; y--) rows.push(Array.from(px.subarray(y * W * 4, (y + 1) * W * 4)));
      out.push(rows);
    }
    gl.bindFramebuffer(gl.READ_FRAMEBUFFER, null);
    return out;
  },
  benchmark(n, dAz = 360 / n) { const t0 = performance.now(); for (let i = 0; i < n; i++) { this.viewer.orbit(dAz, 0); this.viewer.draw(); } return (performance.now() - t0) / n; },
};
Object.defineProperty(window.opacityhull, "lastFrameMs", { get() { return this.viewer ? this.viewer.lastFrameMs : null; } });
window.opacityhull.ready.catch(() => {});
window.addEventListener("error", (e) => showError(String(e.message || e)));
main().then((v) => { window.opacityhull.status = "ready"; resolveReady(v); },
  (err) => { window.opacityhull.status = "error"; showError(err.message || String(err)); rejectReady(err); });
