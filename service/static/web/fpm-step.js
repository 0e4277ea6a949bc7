// The fitted FPM lattice stepped in the browser: fpm/runtime.py (Runtime) ported to JavaScript.
//
// An ES module with no DOM use (it runs in a page or in a Web Worker: live-worker.js). It builds
// a model from the JSON export (`fpmcal export --format json`, or the service's
// GET /v1/parameter-sets/{id}/export?format=json) and steps it as fpm.runtime.Runtime does,
// every node at once, in float64 (positions x, velocities v, forces: Float64Array(3 N), node n's
// components at 3 n, 3 n + 1, 3 n + 2; masses m; the fixed nodes never move):
//
//     F = F_ext + m g + (F_springs(x) + F_volume(x))
//     v <- (v + dt F / m) / (1 + dt d / m)          nodal damping, taken implicitly
//     x <- x + dt v
//
// - springs s = (i, j, L, k): f = k (|r| - L) / |r| r on i and -f on j, r = x_j - x_i;
// - the volume term per hexahedron c (corners in the export's NATURAL order):
//   f_n = -kappa_c (V_c - V0_c) / V0_c dV_c/dx_n, V_c the trilinear hexahedron's volume in
//   closed form, V = 8 [a1, a2, a3] + 8/3 ([a1, a4, a5] + [a4, a2, a6] + [a5, a6, a3]),
//   a_k = sum_n C_kn x_n (C = COEFFICIENTS: +-1/8) and [a, b, c] = a . (b x c).
//
// The arithmetic follows Runtime's term by term: the spring forces are summed per node in spring
// order (Runtime's sparse gather, whose rows are sorted by spring), the volume forces per node in
// hexahedron order, each sum from zero, then F = applied + (springs + volume); the products,
// differences and quotients are Runtime's. Only the small matrix products of the volume term (a_k
// and dV/dx from a_k: BLAS in NumPy, butterflies here) round differently, so the positions agree
// with Runtime's to a few 1e-15 of the displacement after 1,000 steps (tests/web/test_live_step.py
// checks 1e-9 with forces that change every step).
//
// Which d and dt (as Runtime.from_export): the export's parameters.engine, the fastest-settling
// pair of this all-at-once step (fpm.dynamics.engine_damping), where it has one; else, or with
// fromExport(doc, {damping: "kernel"}), parameters.d and dt, the calibration kernel's. The
// model's `damping` says which.
//
// Fast: flat typed arrays, nothing allocated per step (the force buffers are the model's own),
// one pass over the springs (scatter, each node's own run of springs summed in registers), one
// over the hexahedra, one over the nodes.

/** The natural coordinates (r, s, t) of a hexahedron's 8 corners, in the export's order. */
export const NATURAL = [
  [-1, -1, -1], [1, -1, -1], [1, 1, -1], [-1, 1, -1],
  [-1, -1, 1], [1, -1, 1], [1, 1, 1], [-1, 1, 1],
];

/** (6, 8) C_kn, the coefficients of r, s, t, rs, rt, st in a hexahedron's trilinear map. */
export const COEFFICIENTS = [
  NATURAL.map((n) => n[0] / 8),
  NATURAL.map((n) => n[1] / 8),
  NATURAL.map((n) => n[2] / 8),
  NATURAL.map((n) => (n[0] * n[1]) / 8),
  NATURAL.map((n) => (n[0] * n[2]) / 8),
  NATURAL.map((n) => (n[1] * n[2]) / 8),
];

const THIRD = 8.0 / 3.0; // the weight of the three mixed triple products (Runtime's 8.0 / 3.0)

export class ExportFormatError extends Error {}

/** An exported FPM lattice, stepped in time (fpm.runtime.Runtime's fields, flattened). */
export class FpmModel {
  /**
   * @param {object} p
   * @param {Float64Array} p.rest (3 N) rest positions, m
   * @param {Float64Array} p.masses (N) kg
   * @param {Uint8Array} p.fixed (N) 1 for the nodes that never move
   * @param {Int32Array} p.springs (2 S) node pairs i, j
   * @param {Float64Array} p.restLengths (S) m
   * @param {Float64Array} p.stiffness (S) N/m
   * @param {Int32Array} p.corners (8 H) hexahedron corners, NATURAL order (empty: no volume term)
   * @param {Float64Array} p.kappa (H) Pa
   * @param {Float64Array} p.restVolumes (H) m^3
   * @param {number} p.d nodal damping, N s/m
   * @param {number} p.dt time step, s
   * @param {number} p.settleTolerance settled below this times the largest applied force
   * @param {number} [p.settleStiffness] or once the 2-norm of the unbalanced forces is below
   *   this (N/m) times the 2-norm of the displacements (the distance criterion; 0: none)
   * @param {number[]} [p.gravity] m/s^2
   * @param {string} [p.damping] where d and dt came from: "engine", "kernel" or "given"
   */
  constructor(p) {
    this.rest = p.rest;
    this.masses = p.masses;
    this.fixed = p.fixed;
    this.springs = p.springs;
    this.restLengths = p.restLengths;
    this.stiffness = p.stiffness;
    this.corners = p.corners;
    this.kappa = p.kappa;
    this.restVolumes = p.restVolumes;
    this.d = p.d;
    this.dt = p.dt;
    this.damping = p.damping || "given";
    this.settleTolerance = p.settleTolerance;
    this.settleStiffness = p.settleStiffness || 0;
    this.gravity = Float64Array.from(p.gravity || [0, 0, 0]);
    this.nNodes = this.masses.length;
    this.nSprings = this.restLengths.length;
    this.nHexahedra = this.kappa.length;
    const n3 = 3 * this.nNodes;
    this.x = new Float64Array(n3);
    this.v = new Float64Array(n3);
    this.springForce = new Float64Array(n3); // per step: the springs' sum at every node
    this.volumeForce = new Float64Array(n3); // per step: the volume term's
    this.steps = 0;
    this.unbalanced = Infinity;
    this.settled = false;
    this.loadScale = 0;
    this.movedScale = 0;
    this.reset();
  }

  /**
   * The model of a parsed JSON export (`format: "fpm-lattice"`).
   * @param {object} doc the export
   * @param {object} [options]
   * @param {string} [options.damping] "engine" (parameters.engine's d and dt: refused if the
   *   export has none), "kernel" (parameters.d and dt), or unset: the engine's where the export
   *   carries them, else the kernel's
   */
  static fromExport(doc, options = {}) {
    if (!doc || doc.format !== "fpm-lattice") {
      throw new ExportFormatError("not an FPM lattice export (its format is not 'fpm-lattice')");
    }
    const p = doc.parameters;
    const engine = p.engine || null;
    const damping = options.damping || (engine ? "engine" : "kernel");
    if (damping !== "engine" && damping !== "kernel") {
      throw new Error(`damping: "engine" or "kernel", not ${JSON.stringify(damping)}`);
    }
    if (damping === "engine" && !engine) {
      throw new ExportFormatError("this export has no parameters.engine block: use damping 'kernel'");
    }
    const chosen = damping === "engine" ? engine : p;
    const n = doc.nodes.length;
    const rest = new Float64Array(3 * n);
    doc.nodes.forEach((node, i) => rest.set(node, 3 * i));
    const fixed = new Uint8Array(n);
    for (const i of doc.fixed) fixed[i] = 1;
    const s = doc.springs.length;
    const springs = new Int32Array(2 * s);
    const restLengths = new Float64Array(s);
    const stiffness = new Float64Array(s);
    doc.springs.forEach((row, k) => {
      springs[2 * k] = row[0];
      springs[2 * k + 1] = row[1];
      restLengths[k] = row[2];
      stiffness[k] = row[3];
    });
    let corners = new Int32Array(0);
    let kappa = new Float64Array(0);
    let restVolumes = new Float64Array(0);
    if (doc.volume_stiffness !== null && doc.volume_stiffness !== undefined) {
      corners = new Int32Array(8 * doc.hexahedra.length);
      doc.hexahedra.forEach((hex, c) => corners.set(hex, 8 * c));
      kappa = Float64Array.from(doc.volume_stiffness);
      restVolumes = Float64Array.from(doc.rest_volumes);
    }
    return new FpmModel({
      rest,
      masses: Float64Array.from(doc.masses),
      fixed,
      springs,
      restLengths,
      stiffness,
      corners,
      kappa,
      restVolumes,
      d: Number(chosen.d),
      dt: Number(chosen.dt),
      damping,
      settleTolerance: Number(p.settle_tolerance),
      settleStiffness: Number(p.settle_stiffness || 0),
      gravity: p.gravity || [0, 0, 0],
    });
  }

  /** Back to rest: x = the rest positions, v = 0. */
  reset() {
    this.x.set(this.rest);
    this.v.fill(0);
    this.steps = 0;
    this.unbalanced = Infinity;
    this.settled = false;
    this.loadScale = 0;
    this.movedScale = 0;
  }

  /** (3 N) the nodal forces of the export's load case `c`, N (into `out` when given). */
  loadCaseForces(doc, c, out = new Float64Array(3 * this.nNodes)) {
    out.fill(0);
    const lc = doc.load_cases[c];
    lc.nodes.forEach((node, k) => out.set(lc.forces[k], 3 * node));
    return out;
  }

  /** For each node, the sum of the stiffness of its springs, N/m (e.g. a drag handle's). */
  /**
   * Per node, the largest force a drag should put on it, N: 0.5 m L / dt^2, L the node's
   * shortest spring. From rest such a force moves the node half of L in one step; a pull of
   * the node's own springs' stiffness times several spacings, applied at once, moves it more
   * and inverts cells (at the engine's dt, about three times the kernel's, a 4 cm pull on the
   * paper's cube diverged within 17 steps; capped so, 20 cm pulls settle).
   */
  stepForceLimit() {
    const shortest = new Float64Array(this.nNodes).fill(Infinity);
    const sp = this.springs;
    for (let s = 0; s < this.nSprings; s++) {
      const length = this.restLengths[s];
      if (length < shortest[sp[2 * s]]) shortest[sp[2 * s]] = length;
      if (length < shortest[sp[2 * s + 1]]) shortest[sp[2 * s + 1]] = length;
    }
    const out = new Float64Array(this.nNodes);
    const scale = 0.5 / (this.dt * this.dt);
    for (let i = 0; i < this.nNodes; i++) {
      out[i] = Number.isFinite(shortest[i]) ? scale * this.masses[i] * shortest[i] : 0;
    }
    return out;
  }

  nodeStiffness() {
    const out = new Float64Array(this.nNodes);
    const sp = this.springs;
    for (let s = 0; s < this.nSprings; s++) {
      out[sp[2 * s]] += this.stiffness[s];
      out[sp[2 * s + 1]] += this.stiffness[s];
    }
    return out;
  }

  /** Spring forces at positions x, summed per node in spring order into this.springForce.
   *  Consecutive springs of one node i (the export lists them so) add to a running sum that is
   *  stored when i changes: the same additions in the same order as one += per spring. */
  _springs(x) {
    const f = this.springForce;
    const sp = this.springs;
    const len0 = this.restLengths;
    const k = this.stiffness;
    const count = this.nSprings;
    f.fill(0);
    let i = -1;
    let s0 = 0, s1 = 0, s2 = 0; // node i's running sum
    let xi0 = 0, xi1 = 0, xi2 = 0;
    for (let s = 0; s < count; s++) {
      const si = 3 * sp[2 * s];
      if (si !== i) {
        if (i >= 0) {
          f[i] = s0;
          f[i + 1] = s1;
          f[i + 2] = s2;
        }
        i = si;
        s0 = f[i];
        s1 = f[i + 1];
        s2 = f[i + 2];
        xi0 = x[i];
        xi1 = x[i + 1];
        xi2 = x[i + 2];
      }
      const j = 3 * sp[2 * s + 1];
      const r0 = x[j] - xi0;
      const r1 = x[j + 1] - xi1;
      const r2 = x[j + 2] - xi2;
      const length = Math.sqrt(r0 * r0 + r1 * r1 + r2 * r2);
      const c = (k[s] * (length - len0[s])) / length;
      const f0 = c * r0;
      const f1 = c * r1;
      const f2 = c * r2;
      s0 += f0;
      s1 += f1;
      s2 += f2;
      f[j] -= f0;
      f[j + 1] -= f1;
      f[j + 2] -= f2;
    }
    if (i >= 0) {
      f[i] = s0;
      f[i + 1] = s1;
      f[i + 2] = s2;
    }
  }

  /** The volume term at positions x, summed per node in hexahedron order into this.volumeForce. */
  _volume(x) {
    const f = this.volumeForce;
    const corners = this.corners;
    const kappa = this.kappa;
    const v0 = this.restVolumes;
    const count = this.nHexahedra;
    f.fill(0);
    for (let c = 0; c < count; c++) {
      const b = 8 * c;
      const n0 = 3 * corners[b];
      const n1 = 3 * corners[b + 1];
      const n2 = 3 * corners[b + 2];
      const n3 = 3 * corners[b + 3];
      const n4 = 3 * corners[b + 4];
      const n5 = 3 * corners[b + 5];
      const n6 = 3 * corners[b + 6];
      const n7 = 3 * corners[b + 7];
      // a_k (k = 1..6: r, s, t, rs, rt, st) = sum_n C_kn x_n, C_kn = +-1/8, component by
      // component as a butterfly over the corners in tensor order (r fastest: 0 1 3 2 4 5 7 6):
      // sums and differences along r, then s, then t (22 additions, not 42).
      let t0 = x[n0], t1 = x[n1], t2 = x[n3], t3 = x[n2];
      let t4 = x[n4], t5 = x[n5], t6 = x[n7], t7 = x[n6];
      let A0 = t0 + t1, B0 = t1 - t0, A1 = t2 + t3, B1 = t3 - t2;
      let A2 = t4 + t5, B2 = t5 - t4, A3 = t6 + t7, B3 = t7 - t6;
      const a1x = 0.125 * ((B0 + B1) + (B2 + B3));
      const a2x = 0.125 * ((A1 - A0) + (A3 - A2));
      const a3x = 0.125 * ((A2 + A3) - (A0 + A1));
      const a4x = 0.125 * ((B1 - B0) + (B3 - B2));
      const a5x = 0.125 * ((B2 + B3) - (B0 + B1));
      const a6x = 0.125 * ((A3 - A2) - (A1 - A0));
      t0 = x[n0 + 1]; t1 = x[n1 + 1]; t2 = x[n3 + 1]; t3 = x[n2 + 1];
      t4 = x[n4 + 1]; t5 = x[n5 + 1]; t6 = x[n7 + 1]; t7 = x[n6 + 1];
      A0 = t0 + t1; B0 = t1 - t0; A1 = t2 + t3; B1 = t3 - t2;
      A2 = t4 + t5; B2 = t5 - t4; A3 = t6 + t7; B3 = t7 - t6;
      const a1y = 0.125 * ((B0 + B1) + (B2 + B3));
      const a2y = 0.125 * ((A1 - A0) + (A3 - A2));
      const a3y = 0.125 * ((A2 + A3) - (A0 + A1));
      const a4y = 0.125 * ((B1 - B0) + (B3 - B2));
      const a5y = 0.125 * ((B2 + B3) - (B0 + B1));
      const a6y = 0.125 * ((A3 - A2) - (A1 - A0));
      t0 = x[n0 + 2]; t1 = x[n1 + 2]; t2 = x[n3 + 2]; t3 = x[n2 + 2];
      t4 = x[n4 + 2]; t5 = x[n5 + 2]; t6 = x[n7 + 2]; t7 = x[n6 + 2];
      A0 = t0 + t1; B0 = t1 - t0; A1 = t2 + t3; B1 = t3 - t2;
      A2 = t4 + t5; B2 = t5 - t4; A3 = t6 + t7; B3 = t7 - t6;
      const a1z = 0.125 * ((B0 + B1) + (B2 + B3));
      const a2z = 0.125 * ((A1 - A0) + (A3 - A2));
      const a3z = 0.125 * ((A2 + A3) - (A0 + A1));
      const a4z = 0.125 * ((B1 - B0) + (B3 - B2));
      const a5z = 0.125 * ((B2 + B3) - (B0 + B1));
      const a6z = 0.125 * ((A3 - A2) - (A1 - A0));

      // Runtime's TRIPLES (p, q, r, w): (a1, a2, a3, 8), (a1, a4, a5, 8/3), (a4, a2, a6, 8/3),
      // (a5, a6, a3, 8/3). Each: qr = a_q x a_r, V += w a_p . qr, and to the gradient
      // g_p += w qr, g_q += w a_r x a_p, g_r += w a_p x a_q (Runtime's order of additions).
      // Triple 1: qr = a2 x a3.
      let qx = a2y * a3z - a2z * a3y, qy = a2z * a3x - a2x * a3z, qz = a2x * a3y - a2y * a3x;
      let volume = 8.0 * (a1x * qx + a1y * qy + a1z * qz);
      let g1x = 8.0 * qx, g1y = 8.0 * qy, g1z = 8.0 * qz;
      let g2x = 8.0 * (a3y * a1z - a3z * a1y);
      let g2y = 8.0 * (a3z * a1x - a3x * a1z);
      let g2z = 8.0 * (a3x * a1y - a3y * a1x);
      let g3x = 8.0 * (a1y * a2z - a1z * a2y);
      let g3y = 8.0 * (a1z * a2x - a1x * a2z);
      let g3z = 8.0 * (a1x * a2y - a1y * a2x);
      // Triple 2: qr = a4 x a5.
      qx = a4y * a5z - a4z * a5y; qy = a4z * a5x - a4x * a5z; qz = a4x * a5y - a4y * a5x;
      volume += THIRD * (a1x * qx + a1y * qy + a1z * qz);
      g1x += THIRD * qx; g1y += THIRD * qy; g1z += THIRD * qz;
      let g4x = THIRD * (a5y * a1z - a5z * a1y);
      let g4y = THIRD * (a5z * a1x - a5x * a1z);
      let g4z = THIRD * (a5x * a1y - a5y * a1x);
      let g5x = THIRD * (a1y * a4z - a1z * a4y);
      let g5y = THIRD * (a1z * a4x - a1x * a4z);
      let g5z = THIRD * (a1x * a4y - a1y * a4x);
      // Triple 3: qr = a2 x a6 (p = a4).
      qx = a2y * a6z - a2z * a6y; qy = a2z * a6x - a2x * a6z; qz = a2x * a6y - a2y * a6x;
      volume += THIRD * (a4x * qx + a4y * qy + a4z * qz);
      g4x += THIRD * qx; g4y += THIRD * qy; g4z += THIRD * qz;
      g2x += THIRD * (a6y * a4z - a6z * a4y);
      g2y += THIRD * (a6z * a4x - a6x * a4z);
      g2z += THIRD * (a6x * a4y - a6y * a4x);
      let g6x = THIRD * (a4y * a2z - a4z * a2y);
      let g6y = THIRD * (a4z * a2x - a4x * a2z);
      let g6z = THIRD * (a4x * a2y - a4y * a2x);
      // Triple 4: qr = a6 x a3 (p = a5).
      qx = a6y * a3z - a6z * a3y; qy = a6z * a3x - a6x * a3z; qz = a6x * a3y - a6y * a3x;
      volume += THIRD * (a5x * qx + a5y * qy + a5z * qz);
      g5x += THIRD * qx; g5y += THIRD * qy; g5z += THIRD * qz;
      g6x += THIRD * (a3y * a5z - a3z * a5y);
      g6y += THIRD * (a3z * a5x - a3x * a5z);
      g6z += THIRD * (a3x * a5y - a3y * a5x);
      g3x += THIRD * (a5y * a6z - a5z * a6y);
      g3y += THIRD * (a5z * a6x - a5x * a6z);
      g3z += THIRD * (a5x * a6y - a5y * a6x);

      // f_n = -p dV/dx_n, dV/dx_n = sum_k C_kn g_k (the butterfly backwards: t, s, r; 20
      // additions per component, not 40); -p C_kn = +-p/8 (exact scalings by 1/8).
      const p = (kappa[c] * (volume - v0[c])) / v0[c];
      const q = -p * 0.125;
      let rm = g1x - g5x, rp = g1x + g5x, sm = g2x - g6x, sp = g2x + g6x;
      f[n0] += q * ((-g3x - sm) - (rm - g4x));
      f[n1] += q * ((-g3x - sm) + (rm - g4x));
      f[n2] += q * ((-g3x + sm) + (rm + g4x));
      f[n3] += q * ((-g3x + sm) - (rm + g4x));
      f[n4] += q * ((g3x - sp) - (rp - g4x));
      f[n5] += q * ((g3x - sp) + (rp - g4x));
      f[n6] += q * ((g3x + sp) + (rp + g4x));
      f[n7] += q * ((g3x + sp) - (rp + g4x));
      rm = g1y - g5y; rp = g1y + g5y; sm = g2y - g6y; sp = g2y + g6y;
      f[n0 + 1] += q * ((-g3y - sm) - (rm - g4y));
      f[n1 + 1] += q * ((-g3y - sm) + (rm - g4y));
      f[n2 + 1] += q * ((-g3y + sm) + (rm + g4y));
      f[n3 + 1] += q * ((-g3y + sm) - (rm + g4y));
      f[n4 + 1] += q * ((g3y - sp) - (rp - g4y));
      f[n5 + 1] += q * ((g3y - sp) + (rp - g4y));
      f[n6 + 1] += q * ((g3y + sp) + (rp + g4y));
      f[n7 + 1] += q * ((g3y + sp) - (rp + g4y));
      rm = g1z - g5z; rp = g1z + g5z; sm = g2z - g6z; sp = g2z + g6z;
      f[n0 + 2] += q * ((-g3z - sm) - (rm - g4z));
      f[n1 + 2] += q * ((-g3z - sm) + (rm - g4z));
      f[n2 + 2] += q * ((-g3z + sm) + (rm + g4z));
      f[n3 + 2] += q * ((-g3z + sm) - (rm + g4z));
      f[n4 + 2] += q * ((g3z - sp) - (rp - g4z));
      f[n5 + 2] += q * ((g3z - sp) + (rp - g4z));
      f[n6 + 2] += q * ((g3z + sp) + (rp + g4z));
      f[n7 + 2] += q * ((g3z + sp) - (rp + g4z));
    }
  }

  /** (3 N) spring and volume forces at positions `x` (3 N), N, into `out` (Runtime's
   *  internal_forces: -dE/dx without the applied forces). */
  internalForces(x = this.x, out = new Float64Array(3 * this.nNodes)) {
    this._springs(x);
    out.set(this.springForce);
    if (this.nHexahedra > 0) {
      this._volume(x);
      const fv = this.volumeForce;
      for (let k = 0; k < out.length; k++) out[k] += fv[k];
    }
    return out;
  }

  /**
   * Advance one step under the external nodal `forces` (Float64Array(3 N), N; null: none).
   * Sets unbalanced (the largest |F_i| over the free nodes at the start of the step) and
   * settled (unbalanced under settleTolerance times the largest applied nodal force of this
   * step, or of the last loaded step when the forces are zero; or the 2-norm of the unbalanced
   * forces under settleStiffness times the 2-norm of the displacements, of the last loaded
   * step when the forces are zero), as Runtime does.
   * @returns {Float64Array} the positions after the step (the model's own array: read only)
   */
  step(forces = null) {
    const x = this.x;
    const v = this.v;
    this._springs(x);
    const volume = this.nHexahedra > 0;
    if (volume) this._volume(x);
    const fs = this.springForce;
    const fv = this.volumeForce;
    const m = this.masses;
    const fixed = this.fixed;
    const dt = this.dt;
    const d = this.d;
    const g0 = this.gravity[0], g1 = this.gravity[1], g2 = this.gravity[2];
    const external = forces !== null && forces !== undefined;
    let worst = 0;
    let total = 0;
    let moved = 0; // the displacements' squared 2-norm at the step's start
    let load = 0;
    const rest = this.rest;
    const n = this.nNodes;
    for (let i = 0; i < n; i++) {
      if (fixed[i]) continue; // total 0, v 0: x stays at rest
      const k = 3 * i;
      const mi = m[i];
      let p0 = mi * g0, p1 = mi * g1, p2 = mi * g2; // applied: m g + F_ext
      if (external) {
        p0 += forces[k];
        p1 += forces[k + 1];
        p2 += forces[k + 2];
      }
      let i0 = fs[k], i1 = fs[k + 1], i2 = fs[k + 2];
      if (volume) {
        i0 += fv[k];
        i1 += fv[k + 1];
        i2 += fv[k + 2];
      }
      const t0 = p0 + i0, t1 = p1 + i1, t2 = p2 + i2;
      const f2 = t0 * t0 + t1 * t1 + t2 * t2;
      if (f2 > worst) worst = f2;
      total += f2;
      const u0 = x[k] - rest[k], u1 = x[k + 1] - rest[k + 1], u2 = x[k + 2] - rest[k + 2];
      moved += u0 * u0 + u1 * u1 + u2 * u2;
      const l2 = p0 * p0 + p1 * p1 + p2 * p2;
      if (l2 > load) load = l2;
      const a = dt / mi;
      const damp = 1.0 + a * d;
      const v0 = (v[k] + a * t0) / damp;
      const v1 = (v[k + 1] + a * t1) / damp;
      const v2 = (v[k + 2] + a * t2) / damp;
      v[k] = v0;
      v[k + 1] = v1;
      v[k + 2] = v2;
      x[k] += dt * v0;
      x[k + 1] += dt * v1;
      x[k + 2] += dt * v2;
    }
    this.unbalanced = Math.sqrt(worst);
    load = Math.sqrt(load);
    if (load > 0) {
      this.loadScale = load;
      this.movedScale = Math.sqrt(moved); // unloaded, the equilibrium is rest: keep the last
    }
    this.settled =
      this.unbalanced < this.settleTolerance * this.loadScale ||
      Math.sqrt(total) < this.settleStiffness * this.movedScale;
    this.steps += 1;
    return x;
  }

  /** Step under constant `forces` until settled or `maxSteps`; the steps taken. */
  run(forces = null, maxSteps = 100000) {
    for (let n = 1; n <= maxSteps; n++) {
      this.step(forces);
      if (this.settled) return n;
    }
    return maxSteps;
  }
}
