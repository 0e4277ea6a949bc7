// The web view's 3D view of a parameter set: the lattice's outer surface drawn with three.js
// (vendor/three: three@0.170.0, served from this origin), per load case the FEM reference's
// shape, the settled FPM shape or both, coloured by the per-node discrepancy |p_i − q_i|.
//
// An ES module, loaded by app.js (import("./view3d.js")) only when a 3D view is opened. app.js
// fetches the data (GET /v1/parameter-sets/{id}/view: 202 until a worker has made it) and hands
// the ArrayBuffer to decodeView(); mountView() builds the controls, the canvas and the legend
// around a View3D, which owns the three.js scene. View3D.setNodePositions() takes a lattice's
// node positions from elsewhere (e.g. a live model in a Web Worker) and draws them in place of
// the stored FPM shape.
//
// The body (worker/view.py): "FPMV", a little-endian uint32 header length, the header (JSON:
// counts, h, bounds, cases with their figures, each array's dtype, shape and byte offset), then
// the little-endian float32 / uint32 arrays. Vertices are lattice nodes: the surface nodes
// first (the only ones the triangles use), then fixed and loaded nodes off the surface;
// node_index gives each vertex's lattice node.
import * as THREE from "./vendor/three/three.module.min.js";
import { OrbitControls } from "./vendor/three/OrbitControls.js";

const MAGIC = "FPMV";
const TYPES = { float32: Float32Array, uint32: Uint32Array };
const LITTLE_ENDIAN = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;

// ---- Decoding -------------------------------------------------------------------------------

function typedArray(buffer, entry) {
  const Type = TYPES[entry.dtype];
  if (!Type) throw new Error(`unknown dtype ${entry.dtype}`);
  const count = entry.shape.reduce((a, b) => a * b, 1);
  if (LITTLE_ENDIAN) return new Type(buffer, entry.offset, count);
  const view = new DataView(buffer, entry.offset, count * 4); // a big-endian machine: copy
  const out = new Type(count);
  const get = entry.dtype === "float32" ? (i) => view.getFloat32(4 * i, true) : (i) => view.getUint32(4 * i, true);
  for (let i = 0; i < count; i++) out[i] = get(i);
  return out;
}

// The view body as {header, positions, triangles, nodeIndex, fixed, cases: [{...header's, fem,
// fpm, loaded, forces}]}: typed arrays over the buffer (no copy).
export function decodeView(buffer) {
  const bytes = new Uint8Array(buffer);
  if (String.fromCharCode(...bytes.subarray(0, 4)) !== MAGIC) throw new Error("not a 3D view body");
  const length = new DataView(buffer).getUint32(4, true);
  const header = JSON.parse(new TextDecoder().decode(bytes.subarray(8, 8 + length)));
  const arrays = {};
  for (const [name, entry] of Object.entries(header.arrays)) arrays[name] = typedArray(buffer, entry);
  return {
    header,
    positions: arrays.positions,
    triangles: arrays.triangles,
    nodeIndex: arrays.node_index,
    fixed: arrays.fixed,
    cases: header.cases.map((c) => ({
      ...c,
      fem: arrays[c.arrays.fem],
      fpm: arrays[c.arrays.fpm],
      loaded: arrays[c.arrays.loaded],
      forces: arrays[c.arrays.forces],
    })),
  };
}

// ---- Colours ----------------------------------------------------------------------------------

// matplotlib's viridis at 11 stops (sRGB), interpolated to 256.
const VIRIDIS = ["#440154", "#482475", "#414487", "#355f8d", "#2a788e", "#21918c", "#22a884",
  "#44bf70", "#7ad151", "#bddf26", "#fde725"];

function rgb(hex) {
  return [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
}

const SRGB_LUT = (() => {
  const stops = VIRIDIS.map(rgb);
  const lut = new Float32Array(256 * 3);
  for (let i = 0; i < 256; i++) {
    const t = (i / 255) * (stops.length - 1);
    const k = Math.min(Math.floor(t), stops.length - 2);
    const f = t - k;
    for (let c = 0; c < 3; c++) lut[3 * i + c] = stops[k][c] * (1 - f) + stops[k + 1][c] * f;
  }
  return lut;
})();

const toLinear = (c) => (c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4);
const LINEAR_LUT = SRGB_LUT.map(toLinear); // vertex colours are linear in three.js

// The colormap's CSS colour at t in [0, 1] (the legend's).
export function colormap(t) {
  const i = Math.max(0, Math.min(255, Math.round(t * 255)));
  const [r, g, b] = [0, 1, 2].map((c) => Math.round(255 * SRGB_LUT[3 * i + c]));
  return `rgb(${r}, ${g}, ${b})`;
}

// ---- The scene --------------------------------------------------------------------------------

const MODES = ["fpm", "fem", "both"];

// Quad edges (each once) of the surface: the triangles come in pairs (a, b, c), (a, c, d).
function quadEdges(triangles, vertices) {
  const seen = new Set();
  const out = [];
  const add = (i, j) => {
    const key = i < j ? i * vertices + j : j * vertices + i;
    if (!seen.has(key)) { seen.add(key); out.push(i, j); }
  };
  for (let t = 0; t + 5 < triangles.length; t += 6) {
    const a = triangles[t], b = triangles[t + 1], c = triangles[t + 2], d = triangles[t + 5];
    add(a, b); add(b, c); add(c, d); add(d, a);
  }
  return new Uint32Array(out);
}

// The mesh's up axis, as a coordinate axis ({vector, name: "+z", why}): against gravity when
// the spec has gravity (the header's), else pointing from the fixed nodes' mean to the centroid of
// the drawn nodes (a solid held at its feet stands on them), else z. Snapped to the nearest axis, so that the
// view's horizon is the lattice's.
export function upAxis(data) {
  const g = data.header.gravity;
  let v = null;
  let why = "z (no gravity, no fixed nodes)";
  if (Array.isArray(g) && Math.hypot(...g) > 0) {
    v = g.map((x) => -x);
    why = "against gravity";
  } else if (data.fixed.length) {
    const p = data.positions;
    const mean = (indices) => {
      const m = [0, 0, 0];
      for (const i of indices) for (let a = 0; a < 3; a++) m[a] += p[3 * i + a] / indices.length;
      return m;
    };
    const all = Array.from({ length: p.length / 3 }, (_, i) => i);
    const fixed = mean(data.fixed);
    const centroid = mean(all);
    const away = centroid.map((c, a) => c - fixed[a]);
    const [lo, hi] = data.header.bounds;
    if (Math.hypot(...away) > 1e-6 * Math.hypot(...hi.map((x, a) => x - lo[a]))) {
      v = away;
      why = "away from the fixed nodes";
    }
  }
  let axis = 2;
  let sign = 1;
  if (v) {
    axis = [0, 1, 2].reduce((best, a) => (Math.abs(v[a]) > Math.abs(v[best]) ? a : best), 0);
    sign = Math.sign(v[axis]) || 1;
  }
  const vector = new THREE.Vector3(0, 0, 0).setComponent(axis, sign);
  return { vector, name: `${sign > 0 ? "+" : "−"}${"xyz"[axis]}`, why };
}

export class View3D {
  // container: an element to fill (its width; height from CSS); data: decodeView()'s answer.
  constructor(container, data) {
    this.data = data;
    this.container = container;
    this.vertices = data.positions.length / 3;
    this.caseIndex = 0;
    this.mode = "fpm";
    this.scale = 1;
    this.saturate = 1; // the colour scale ends at this fraction of the case's largest |p − q|
    this.pushed = null; // displacements from setNodePositions(), shown instead of the FPM's
    this.discrepancy = new Float32Array(this.vertices);

    const renderer = new THREE.WebGLRenderer({ antialias: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    renderer.setClearColor(0xffffff, 1);
    container.append(renderer.domElement);
    this.renderer = renderer;

    const [lo, hi] = data.header.bounds;
    const center = new THREE.Vector3((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2);
    this.radius = 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]) || 1;
    this.center = center;
    const camera = new THREE.PerspectiveCamera(30, 1, this.radius / 100, this.radius * 100);
    this.up = upAxis(data);
    camera.up.copy(this.up.vector);
    this.camera = camera;
    const scene = new THREE.Scene();
    this.scene = scene;
    scene.add(new THREE.AmbientLight(0xffffff, 1.6));
    const headlight = new THREE.DirectionalLight(0xffffff, 1.9);
    headlight.position.set(0.3, 0.4, 1);
    camera.add(headlight); // lights what the camera looks at, from wherever it orbits
    scene.add(camera);

    // The shown surface (FPM, or FEM in "fem" mode), coloured per vertex.
    this.shown = new THREE.BufferAttribute(new Float32Array(3 * this.vertices), 3);
    this.colours = new THREE.BufferAttribute(new Float32Array(3 * this.vertices), 3);
    const surface = new THREE.BufferGeometry();
    surface.setAttribute("position", this.shown);
    surface.setAttribute("color", this.colours);
    surface.setIndex(new THREE.BufferAttribute(data.triangles, 1));
    this.surface = new THREE.Mesh(surface, new THREE.MeshLambertMaterial({
      vertexColors: true, flatShading: true, side: THREE.DoubleSide,
      polygonOffset: true, polygonOffsetFactor: 1, polygonOffsetUnits: 1,
    }));
    scene.add(this.surface);

    const edges = new THREE.BufferAttribute(quadEdges(data.triangles, this.vertices), 1);
    const lattice = new THREE.BufferGeometry();
    lattice.setAttribute("position", this.shown);
    lattice.setIndex(edges);
    this.lattice = new THREE.LineSegments(lattice, new THREE.LineBasicMaterial({
      color: 0xffffff, transparent: true, opacity: 0.3,
    }));
    scene.add(this.lattice);

    // The FEM shape as lines over the FPM's surface ("both").
    this.femShape = new THREE.BufferAttribute(new Float32Array(3 * this.vertices), 3);
    const fem = new THREE.BufferGeometry();
    fem.setAttribute("position", this.femShape);
    fem.setIndex(edges);
    this.femLines = new THREE.LineSegments(fem, new THREE.LineBasicMaterial({ color: 0xd62728 }));
    scene.add(this.femLines);

    // Markers: fixed nodes (small dark cubes), loaded nodes (spheres) with their force's direction.
    const h = data.header.h;
    this.fixedMarkers = new THREE.InstancedMesh(new THREE.BoxGeometry(0.3 * h, 0.3 * h, 0.3 * h),
      new THREE.MeshLambertMaterial({ color: 0x3a4454 }), Math.max(1, data.fixed.length));
    this.fixedMarkers.count = data.fixed.length;
    const most = Math.max(1, ...data.cases.map((c) => c.loaded.length));
    this.loadMarkers = new THREE.InstancedMesh(new THREE.SphereGeometry(0.32 * h, 12, 8),
      new THREE.MeshLambertMaterial({ color: 0xff2a6d }), most);
    const arrows = new THREE.BufferGeometry();
    arrows.setAttribute("position", new THREE.BufferAttribute(new Float32Array(6 * most), 3));
    this.arrows = new THREE.LineSegments(arrows, new THREE.LineBasicMaterial({ color: 0xff2a6d }));
    scene.add(this.fixedMarkers, this.loadMarkers, this.arrows);
    // Their shapes move with the case and the scale factor: never culled on stale bounds.
    for (const o of [this.surface, this.lattice, this.femLines, this.fixedMarkers, this.loadMarkers, this.arrows]) {
      o.frustumCulled = false;
    }

    this.controls = new OrbitControls(camera, renderer.domElement);
    this.controls.addEventListener("change", () => this.render());
    this.resetCamera();
    this.resize = new ResizeObserver(() => this.fit());
    this.resize.observe(container);
    this.fit();
    this.update();
  }

  get case() { return this.data.cases[this.caseIndex]; }

  // One load case (index into data.cases), the shapes shown ("fpm", "fem" or "both"), the
  // displacement scale factor (1 = true scale), the lattice lines and the markers.
  setCase(index) { this.caseIndex = index; this.update(); }
  setMode(mode) { if (MODES.includes(mode)) { this.mode = mode; this.update(); } }
  setScale(scale) { if (Number.isFinite(scale) && scale >= 0) { this.scale = scale; this.update(); } }
  setSaturation(fraction) { if (fraction > 0 && fraction <= 1) { this.saturate = fraction; this.update(); } }
  // The colour scale's top, m: the case's largest |p − q| (over every node) times the saturation.
  colourTop() { return (this.case.discrepancy_max > 0 ? this.case.discrepancy_max : 1) * this.saturate; }
  setLattice(on) { this.lattice.visible = on; this.render(); }
  setMarkers(on) { this.fixedMarkers.visible = this.loadMarkers.visible = this.arrows.visible = on; this.render(); }

  // Node positions from elsewhere (m; absolute, not displacements), drawn instead of the stored
  // FPM shape of the current case (scaled like it) and coloured by their distance from the
  // FEM's: a Float64Array or Float32Array of 3 per lattice node (the model's own order, mapped
  // through node_index) or 3 per vertex. null goes back to the stored FPM shape.
  setNodePositions(positions) {
    if (positions === null) { this.pushed = null; this.update(); return; }
    const v = this.vertices;
    const lattice = positions.length === 3 * this.data.header.nodes;
    if (!lattice && positions.length !== 3 * v) {
      throw new Error(`need 3 x ${this.data.header.nodes} (nodes) or 3 x ${v} (vertices) positions`);
    }
    const rest = this.data.positions;
    const out = this.pushed && this.pushed.length === 3 * v ? this.pushed : new Float32Array(3 * v);
    const index = this.data.nodeIndex;
    for (let i = 0; i < v; i++) {
      const from = 3 * (lattice ? index[i] : i);
      out[3 * i] = positions[from] - rest[3 * i];
      out[3 * i + 1] = positions[from + 1] - rest[3 * i + 1];
      out[3 * i + 2] = positions[from + 2] - rest[3 * i + 2];
    }
    this.pushed = out;
    this.update();
  }

  // The displacements drawn as the FPM's: pushed ones, else the case's stored ones.
  fpmField() { return this.pushed || this.case.fpm; }

  update() {
    const c = this.case;
    const rest = this.data.positions;
    const p = this.fpmField();
    const q = c.fem;
    const s = this.scale;
    const shownField = this.mode === "fem" ? q : p;
    const shown = this.shown.array;
    const femShape = this.femShape.array;
    const colours = this.colours.array;
    const top = this.colourTop();
    for (let i = 0; i < this.vertices; i++) {
      const x = 3 * i;
      const dx = p[x] - q[x], dy = p[x + 1] - q[x + 1], dz = p[x + 2] - q[x + 2];
      const e = Math.sqrt(dx * dx + dy * dy + dz * dz);
      this.discrepancy[i] = e;
      const k = 3 * Math.max(0, Math.min(255, Math.round((255 * e) / top)));
      colours[x] = LINEAR_LUT[k]; colours[x + 1] = LINEAR_LUT[k + 1]; colours[x + 2] = LINEAR_LUT[k + 2];
      for (let a = 0; a < 3; a++) {
        shown[x + a] = rest[x + a] + s * shownField[x + a];
        femShape[x + a] = rest[x + a] + s * q[x + a];
      }
    }
    this.shown.needsUpdate = true;
    this.colours.needsUpdate = true;
    this.femShape.needsUpdate = true;
    this.femLines.visible = this.mode === "both";
    this.placeMarkers();
    this.render();
  }

  placeMarkers() {
    const shown = this.shown.array;
    const m = new THREE.Matrix4();
    const at = (i) => m.makeTranslation(shown[3 * i], shown[3 * i + 1], shown[3 * i + 2]);
    this.data.fixed.forEach((vertex, j) => this.fixedMarkers.setMatrixAt(j, at(vertex)));
    this.fixedMarkers.instanceMatrix.needsUpdate = true;
    const c = this.case;
    this.loadMarkers.count = c.loaded.length;
    const h = this.data.header.h;
    const ends = this.arrows.geometry.attributes.position;
    c.loaded.forEach((vertex, j) => {
      this.loadMarkers.setMatrixAt(j, at(vertex));
      const f = c.forces.subarray(3 * j, 3 * j + 3);
      const norm = Math.hypot(f[0], f[1], f[2]) || 1;
      for (let a = 0; a < 3; a++) {
        ends.array[6 * j + a] = shown[3 * vertex + a];
        ends.array[6 * j + 3 + a] = shown[3 * vertex + a] + (1.5 * h * f[a]) / norm;
      }
    });
    this.loadMarkers.instanceMatrix.needsUpdate = true;
    ends.needsUpdate = true;
    this.arrows.geometry.setDrawRange(0, 2 * c.loaded.length);
    this.arrows.geometry.computeBoundingSphere();
  }

  resetCamera() {
    // From the front, a little to the side and above, as seen with z up, turned to the up axis.
    const turn = new THREE.Quaternion().setFromUnitVectors(new THREE.Vector3(0, 0, 1), this.up.vector);
    const direction = new THREE.Vector3(1.1, -1.7, 0.9).normalize().applyQuaternion(turn);
    const distance = (1.15 * this.radius) / Math.sin(THREE.MathUtils.degToRad(this.camera.fov / 2));
    this.camera.position.copy(this.center).addScaledVector(direction, distance);
    this.controls.target.copy(this.center);
    this.controls.update();
    this.render();
  }

  fit() {
    const width = Math.max(1, this.container.clientWidth);
    const height = Math.max(1, this.container.clientHeight);
    this.renderer.setSize(width, height, true);
    this.camera.aspect = width / height;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  // Draws at the next animation frame, once however often it is asked before then.
  render() {
    if (this.frame || !this.renderer) return;
    this.frame = requestAnimationFrame(() => {
      this.frame = 0;
      if (!this.renderer) return;
      this.renderer.render(this.scene, this.camera);
      this.frames = (this.frames || 0) + 1;
      this.container.dataset.frames = String(this.frames); // frames drawn (tests wait on it)
    });
  }

  dispose() {
    cancelAnimationFrame(this.frame);
    this.resize.disconnect();
    this.controls.dispose();
    this.scene.traverse((o) => {
      if (o.geometry) o.geometry.dispose();
      if (o.material) o.material.dispose();
    });
    this.renderer.dispose();
    this.renderer.domElement.remove();
    this.renderer = null;
  }
}

// ---- The page around it -----------------------------------------------------------------------

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (name.startsWith("on")) node.addEventListener(name.slice(2), value);
    else node.setAttribute(name, value === true ? "" : String(value));
  }
  for (const child of children.flat(Infinity)) {
    if (child === null || child === undefined || child === false) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

function num(x, digits = 4) {
  if (x === null || x === undefined || !Number.isFinite(Number(x))) return "–";
  const v = Number(x);
  if (v !== 0 && (Math.abs(v) >= 1e6 || Math.abs(v) < 1e-3)) return v.toExponential(digits - 1);
  return String(Number(v.toPrecision(digits)));
}

const pct = (x, digits = 2) => (Number.isFinite(x) ? `${x.toFixed(digits)}%` : "–");

const LEGEND_TICKS = [0, 0.25, 0.5, 0.75, 1];

function legend(view) {
  const c = view.case;
  const top = view.colourTop();
  const bar = el("canvas", { width: 256, height: 1, class: "view3d-ramp", "aria-hidden": "true" });
  const g = bar.getContext("2d");
  for (let i = 0; i < 256; i++) { g.fillStyle = colormap(i / 255); g.fillRect(i, 0, 1, 1); }
  const femMax = c.fem_max > 0 ? c.fem_max : NaN;
  return el("div", { class: "view3d-legend", id: "view3d-legend" },
    el("div", { class: "view3d-legend-title" },
      "Discrepancy |p", el("sub", null, "i"), " − q", el("sub", null, "i"), "| per node (FPM − FEM): m, and % of the case's largest FEM displacement (",
      `${num(c.fem_max)} m)`),
    bar,
    el("div", { class: "view3d-ticks" }, LEGEND_TICKS.map((t) => el("span", { "data-tick": t },
      `${t === 1 && view.saturate < 1 ? "≥ " : ""}${num(t * top)} m`, el("br"), pct((100 * t * top) / femMax, 1)))),
    el("div", { class: "view3d-keys" },
      el("span", { class: "view3d-key fixed" }, "■"), " fixed nodes  ",
      el("span", { class: "view3d-key loaded" }, "●"), " loaded nodes, the line along their force  ",
      el("span", { class: "view3d-key fem" }, "—"), " FEM shape (with “both”)"));
}

const count = (n) => Number(n).toLocaleString("en-US");

// The figures above the view: the calibration's own (its result's settle steps, ``steps``: one
// per fitted case, from options.settleSteps) where the page has them, else this view's run's.
function caseFacts(view, steps) {
  const c = view.case;
  const validation = c.kind === "validation";
  const settled = Number.isFinite(steps?.[view.caseIndex])
    ? `FPM settled in ${count(steps[view.caseIndex])} steps (the calibration's final run)`
    : `FPM ${c.settled ? "settled" : "did not settle"} in ${count(c.steps)} steps (this view's run)`;
  return el("p", { class: "view3d-facts", id: "view3d-facts" },
    el("strong", { class: "headline" }, `${pct(c.relative_discrepancy)} relative discrepancy`),
    validation ? " (validation case: never fitted)" : ` · loaded nodes ${pct(c.loaded_discrepancy)}`,
    ` · ${pct(c.discrepancy_h)} of h · largest FEM displacement ${num(c.fem_max)} m`,
    ` · largest |p − q| ${num(c.discrepancy_max)} m`,
    validation ? ` · FPM: static equilibrium${c.settled ? "" : " (not converged)"}` : ` · ${settled}`);
}

// The 3D view with its controls into ``panel`` (an element): case, shapes, scale factor,
// lattice lines, markers, the legend, and the push mode (live.js, loaded when pressed;
// options.request(path, accept) is the page's fetch with its API key; options.settleSteps the
// calibration result's settle steps per fitted case, shown above the view). Returns the View3D.
export function mountView(panel, data, options = {}) {
  const canvasBox = el("div", { class: "view3d-canvas", id: "view3d-canvas" });
  const facts = el("div");
  const legendBox = el("div");
  const caseSelect = el("select", { id: "view3d-case" }, data.cases.map((c, i) =>
    el("option", { value: i }, `${c.name} (${c.kind})`)));
  const modeBox = el("span", { class: "view3d-modes" }, [["fpm", "FPM (settled)"], ["fem", "FEM reference"], ["both", "both"]]
    .map(([mode, label]) => el("label", null, el("input", {
      type: "radio", name: "view3d-mode", value: mode, checked: mode === "fpm", "data-mode": mode,
    }), ` ${label}`)));
  const scaleRange = el("input", { type: "range", min: 0, max: 20, step: 0.1, value: 1, id: "view3d-scale-range" });
  const scaleNumber = el("input", { type: "number", min: 0, step: "any", value: 1, id: "view3d-scale", class: "view3d-scale" });
  const saturation = el("select", { id: "view3d-saturate" }, [[1, "the largest |p − q|"], [0.5, "½ of it"],
    [0.25, "¼ of it"], [0.1, "1/10 of it"]].map(([f, label]) => el("option", { value: f }, label)));
  const lines = el("input", { type: "checkbox", checked: true, id: "view3d-lines" });
  const markers = el("input", { type: "checkbox", checked: true, id: "view3d-markers" });
  const reset = el("button", { type: "button", id: "view3d-reset" }, "Reset view");
  const push = el("button", { type: "button", id: "view3d-push", "aria-pressed": "false" }, "Push (live)");
  const h = data.header;
  panel.append(
    el("div", { class: "toolbar view3d-toolbar" },
      el("label", null, "Load case ", caseSelect), modeBox,
      el("label", null, "Displacement scale ", scaleRange, " ", scaleNumber, " ×"),
      el("label", null, "Colours up to ", saturation),
      el("label", null, lines, " lattice lines"), el("label", null, markers, " markers"), reset, push),
    facts, canvasBox, legendBox,
    el("p", { class: "muted" },
      `${h.nodes} nodes, h = ${num(h.h * 1e3)} mm; the outer surface: ${h.surface_vertices} nodes, ${h.triangles} triangles. `,
      "Drag to orbit, wheel or pinch to zoom, right-drag to pan. FPM: the run at the set's parameters from rest to ",
      "settling (fitted cases), the static equilibrium (validation cases). ",
      el("span", { id: "view3d-up" })));
  const view = new View3D(canvasBox, data);
  panel.querySelector("#view3d-up").textContent = `Up: ${view.up.name} (${view.up.why}).`;
  panel.dataset.up = view.up.name;
  const refresh = () => {
    facts.replaceChildren(caseFacts(view, options.settleSteps));
    legendBox.replaceChildren(legend(view));
    panel.dataset.case = String(view.caseIndex);
    panel.dataset.mode = view.mode;
    panel.dataset.scale = String(view.scale);
  };
  caseSelect.addEventListener("change", () => { view.setCase(Number(caseSelect.value)); refresh(); });
  modeBox.addEventListener("change", (event) => { view.setMode(event.target.value); refresh(); });
  const scaleTo = (value) => {
    const s = Number(value);
    if (!Number.isFinite(s) || s < 0) return;
    view.setScale(s);
    scaleRange.value = String(Math.min(s, 20));
    scaleNumber.value = String(s);
    refresh();
  };
  scaleRange.addEventListener("input", () => scaleTo(scaleRange.value));
  scaleNumber.addEventListener("change", () => scaleTo(scaleNumber.value));
  saturation.addEventListener("change", () => { view.setSaturation(Number(saturation.value)); refresh(); });
  lines.addEventListener("change", () => view.setLattice(lines.checked));
  markers.addEventListener("change", () => view.setMarkers(markers.checked));
  reset.addEventListener("click", () => view.resetCamera());
  push.addEventListener("click", () => import("./live.js").then((live) => live.togglePush(view, push, options)));
  refresh();
  return view;
}
