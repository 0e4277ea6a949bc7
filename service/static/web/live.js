// The 3D view's push mode: the fitted model live in a Web Worker, a surface node dragged with
// the pointer, the lattice redrawn from the worker's positions every frame.
//
// An ES module, loaded by view3d.js's "Push (live)" button only when it is pressed:
// togglePush(view, button, {request}) starts or stops the mode on a View3D. Starting it fetches
// the parameter set's JSON export (GET v1/parameter-sets/{id}/export?format=json: 202 while a
// worker makes it, asked again after Retry-After; `request` is the page's fetch with its API
// key, plain fetch without), hands the bytes to live-worker.js (a module worker stepping
// fpm-step.js, fpm.runtime's step in JavaScript, at the export's engine d and dt (the
// all-at-once step's fastest-settling pair; the kernel's fitted ones in an export without
// them), at most in real time), and
// from then on:
//   - a pointer pressed on the surface grabs the nearest node of the triangle under it (fixed
//     nodes cannot be grabbed): while the pointer moves, the node is pulled toward it by a
//     spring-like force in the plane facing the camera (k = the node's own springs' stiffness);
//     released, the model swings back to rest. A press off the surface orbits, as before;
//   - every frame the worker posts, the view draws its positions (View3D.setNodePositions; the
//     colours stay the distance to the FEM shape of the shown load case).
// Stopping terminates the worker and shows the stored FPM shape again.
import * as THREE from "./vendor/three/three.module.min.js";

function text(node, value) {
  node.textContent = value;
}

function fmt(value, digits = 3) {
  if (!Number.isFinite(value)) return "–";
  if (value !== 0 && (Math.abs(value) >= 1e5 || Math.abs(value) < 1e-3)) return value.toExponential(digits - 1);
  return String(Number(value.toPrecision(digits)));
}

export class PushMode {
  // view: a View3D; panel: where its status line goes (after `after`); request(path, accept):
  // the page's fetch (API key, 401 handling), or null for fetch().
  constructor(view, { after, request = null } = {}) {
    this.view = view;
    this.request = request;
    this.worker = null;
    this.model = null; // the worker's "ready": nodes, dt, ...
    this.grab = null; // {vertex, node, plane, offset, target}
    this.frames = 0;
    this.history = []; // [time ms, steps] of the last second's frames: the rate achieved
    this.stopped = false;
    this.status = document.createElement("p");
    this.status.className = "muted view3d-live";
    this.status.id = "view3d-live";
    this.intro = document.createElement("span"); // what the mode is
    this.state = document.createElement("span"); // what the model does now
    this.state.id = "view3d-live-state";
    this.status.append(this.intro, this.state);
    this.line = new THREE.Line(
      new THREE.BufferGeometry().setAttribute("position", new THREE.BufferAttribute(new Float32Array(6), 3)),
      new THREE.LineBasicMaterial({ color: 0xd62728 }),
    );
    this.line.visible = false;
    this.line.frustumCulled = false;
    this.raycaster = new THREE.Raycaster();
    this.fixedVertex = new Set(view.data.fixed);
    this.onDown = (event) => this.pointerDown(event);
    this.onMove = (event) => this.pointerMove(event);
    this.onUp = (event) => this.pointerUp(event);
    if (after) after.after(this.status);
    this.container = view.container;
    this.container.dataset.live = "loading";
  }

  say(message) {
    text(this.intro, message);
    text(this.state, "");
  }

  exportPath() {
    const id = this.view.data.header.parameter_set_id;
    if (!id) throw new Error("the view does not say its parameter set");
    return `v1/parameter-sets/${encodeURIComponent(id)}/export?format=json`;
  }

  async fetchExport() {
    const started = performance.now();
    const path = this.exportPath();
    for (;;) {
      const response = this.request
        ? await this.request(path, "application/json")
        : await fetch(path, { headers: { Accept: "application/json" } });
      if (this.stopped) return null;
      if (response.status === 202) {
        const wait = Math.max(1, Number(response.headers.get("Retry-After") || "1"));
        this.say(`A worker is making the model's export (${Math.round((performance.now() - started) / 1000)} s)…`);
        await new Promise((resolve) => setTimeout(resolve, 1000 * wait));
        if (this.stopped) return null;
        continue;
      }
      if (!response.ok) throw new Error(`the export: ${response.status} ${response.statusText}`);
      return response.arrayBuffer();
    }
  }

  async start() {
    this.say("Fetching the model's export…");
    const buffer = await this.fetchExport();
    if (!buffer) return;
    this.say(`Loading the model (${fmt(buffer.byteLength / 1e6)} MB)…`);
    const worker = new Worker(new URL("./live-worker.js", import.meta.url), { type: "module" });
    this.worker = worker;
    const ready = new Promise((resolve, reject) => {
      worker.onerror = (event) => reject(new Error(event.message || "the live model's worker failed"));
      worker.onmessage = (event) => {
        const m = event.data;
        if (m.type === "ready") resolve(m);
        else if (m.type === "frame") this.frame(m);
        else if (m.type === "error") {
          if (this.model) this.say(`Live model: ${m.message}`);
          else reject(new Error(m.message));
        }
      };
    });
    worker.postMessage({ type: "config", realtime: true });
    worker.postMessage({ type: "load", buffer }, [buffer]);
    const model = await ready;
    if (this.stopped) return;
    if (model.nodes !== this.view.data.header.nodes) {
      throw new Error(`the export has ${model.nodes} nodes, the view ${this.view.data.header.nodes}`);
    }
    this.model = model;
    this.view.scene.add(this.line);
    // Capture phase on the container: a press on the surface never reaches OrbitControls.
    this.container.addEventListener("pointerdown", this.onDown, true);
    this.container.dataset.live = "ready";
    const which = model.damping === "engine" ? "the engine's" : "the fitted";
    this.say(`Live: ${model.nodes.toLocaleString()} nodes, stepped at ${which} dt = ` +
      `${fmt(model.dt * 1e3)} ms in a worker. Drag a surface node to pull it; a drag off the ` +
      "surface orbits. ");
    text(this.state, "At rest.");
  }

  stop() {
    this.stopped = true;
    if (this.worker) this.worker.terminate();
    this.worker = null;
    this.container.removeEventListener("pointerdown", this.onDown, true);
    this.release();
    this.view.scene.remove(this.line);
    this.line.geometry.dispose();
    this.line.material.dispose();
    this.status.remove();
    delete this.container.dataset.live;
    this.view.setNodePositions(null);
  }

  // A frame from the worker: draw it, hand the buffer back, say how fast it runs.
  frame(m) {
    if (this.stopped) return;
    this.view.setNodePositions(m.positions); // copied into the view's own displacements
    this.drawLine();
    this.worker.postMessage({ type: "recycle", buffer: m.positions.buffer }, [m.positions.buffer]);
    this.frames += 1;
    this.container.dataset.liveFrames = String(this.frames);
    this.container.dataset.liveSteps = String(m.steps);
    let moved = 0; // the largest displacement drawn, m (as the view holds it: per vertex)
    for (const u of this.view.pushed) moved = Math.max(moved, Math.abs(u));
    this.container.dataset.liveMoved = String(moved);
    if (!this.model) return;
    // Steps per second achieved over the last second (the worker keeps to real time at most),
    // and what the step alone runs at (its time within the frames).
    const now = performance.now();
    this.history.push([now, m.steps]);
    while (this.history.length > 2 && now - this.history[0][0] > 1000) this.history.shift();
    const [t0, s0] = this.history[0];
    const rate = now > t0 ? (1000 * (m.steps - s0)) / (now - t0) : 0;
    const resting = m.stepsThisFrame === 0 || (!this.grab && m.settled);
    const state = this.grab ? `Pulling node ${this.grab.node} with ${fmt(m.dragForce)} N`
      : resting ? "At rest" : "Swinging back";
    const speed = !resting && rate > 0 ? ` · ${Math.round(rate).toLocaleString()} steps/s ` +
      `(${fmt(rate * this.model.dt, 2)}× real time; the step alone runs at ` +
      `${Math.round(m.stepsPerSecond).toLocaleString()}/s)` : "";
    const force = Number.isFinite(m.unbalanced) ? ` · largest unbalanced force ${fmt(m.unbalanced)} N` : "";
    text(this.state, `${state}${speed}${force} · step ${m.steps.toLocaleString()}.`);
  }

  // The pointer's ray (NDC from the event) in the view's camera.
  ray(event) {
    const rect = this.view.renderer.domElement.getBoundingClientRect();
    const ndc = new THREE.Vector2(
      ((event.clientX - rect.left) / rect.width) * 2 - 1,
      -((event.clientY - rect.top) / rect.height) * 2 + 1,
    );
    this.raycaster.setFromCamera(ndc, this.view.camera);
    return this.raycaster.ray;
  }

  // The displayed position of a vertex (what the view draws: rest + scale x displacement).
  shown(vertex) {
    const a = this.view.shown.array;
    return new THREE.Vector3(a[3 * vertex], a[3 * vertex + 1], a[3 * vertex + 2]);
  }

  pointerDown(event) {
    if (event.button !== 0 || !this.model || this.grab) return;
    const geometry = this.view.surface.geometry;
    geometry.computeBoundingSphere(); // the shape moves: never raycast against stale bounds
    if (geometry.boundingBox) geometry.computeBoundingBox();
    this.ray(event);
    const hit = this.raycaster.intersectObject(this.view.surface, false)[0];
    if (!hit || !hit.face) return; // off the surface: OrbitControls orbits
    const candidates = [hit.face.a, hit.face.b, hit.face.c];
    let vertex = candidates[0];
    let best = Infinity;
    for (const v of candidates) {
      const d = this.shown(v).distanceToSquared(hit.point);
      if (d < best) { best = d; vertex = v; }
    }
    event.stopPropagation();
    event.preventDefault();
    if (this.fixedVertex.has(vertex)) {
      this.say("That node is fixed: grab another.");
      return;
    }
    const node = this.view.data.nodeIndex[vertex];
    const at = this.shown(vertex);
    const normal = this.view.camera.getWorldDirection(new THREE.Vector3());
    this.grab = {
      vertex,
      node,
      plane: new THREE.Plane().setFromNormalAndCoplanarPoint(normal, at),
      offset: at.clone().sub(hit.point), // the node stays where it is under the pointer
      target: at.clone(),
      pointer: event.pointerId,
    };
    const canvas = this.view.renderer.domElement;
    canvas.setPointerCapture(event.pointerId);
    canvas.addEventListener("pointermove", this.onMove);
    canvas.addEventListener("pointerup", this.onUp);
    canvas.addEventListener("pointercancel", this.onUp);
    this.container.dataset.live = "dragging";
    this.container.dataset.liveNode = String(node);
    this.pull(this.grab.target);
  }

  pointerMove(event) {
    if (!this.grab || event.pointerId !== this.grab.pointer) return;
    const point = this.ray(event).intersectPlane(this.grab.plane, new THREE.Vector3());
    if (!point) return;
    this.grab.target.copy(point).add(this.grab.offset);
    this.pull(this.grab.target);
  }

  pointerUp(event) {
    if (!this.grab || event.pointerId !== this.grab.pointer) return;
    this.release();
  }

  // Pull the grabbed node toward a displayed point: the model's target is the rest position
  // plus the displayed displacement undone from the view's scale factor.
  pull(display) {
    const { vertex, node } = this.grab;
    const rest = this.view.data.positions;
    const s = this.view.scale > 0 ? this.view.scale : 1;
    const target = [0, 1, 2].map((a) => rest[3 * vertex + a] + (display.getComponent(a) - rest[3 * vertex + a]) / s);
    this.worker.postMessage({ type: "drag", node, target });
    this.drawLine();
  }

  release() {
    if (!this.grab) return;
    const canvas = this.view.renderer && this.view.renderer.domElement;
    if (canvas) {
      canvas.removeEventListener("pointermove", this.onMove);
      canvas.removeEventListener("pointerup", this.onUp);
      canvas.removeEventListener("pointercancel", this.onUp);
      if (canvas.hasPointerCapture(this.grab.pointer)) canvas.releasePointerCapture(this.grab.pointer);
    }
    if (this.worker) this.worker.postMessage({ type: "drag", node: this.grab.node, target: null });
    this.grab = null;
    this.line.visible = false;
    if (this.model) this.container.dataset.live = "ready";
    this.view.render();
  }

  // The pull as a line from the node (as drawn) to the pointer.
  drawLine() {
    if (!this.grab) return;
    const a = this.line.geometry.attributes.position;
    const from = this.shown(this.grab.vertex);
    a.setXYZ(0, from.x, from.y, from.z);
    a.setXYZ(1, this.grab.target.x, this.grab.target.y, this.grab.target.z);
    a.needsUpdate = true;
    this.line.visible = true;
    this.view.render();
  }
}

// The "Push (live)" button's action: start the push mode on `view` (its status line after the
// button's toolbar), or stop it. options.request(path, accept): the page's fetch.
export async function togglePush(view, button, options = {}) {
  if (view.push) {
    view.push.stop();
    view.push = null;
    button.textContent = "Push (live)";
    button.setAttribute("aria-pressed", "false");
    return null;
  }
  const push = new PushMode(view, { after: button.closest(".toolbar") || button, request: options.request || null });
  view.push = push;
  button.textContent = "Stop pushing";
  button.setAttribute("aria-pressed", "true");
  if (!view.disposeView) { // leaving the 3D view stops the worker too
    view.disposeView = view.dispose.bind(view);
    view.dispose = () => { if (view.push) view.push.stop(); view.push = null; view.disposeView(); };
  }
  try {
    await push.start();
  } catch (error) {
    push.say(`The live model could not start: ${error.message || error}`);
    push.container.dataset.live = "failed";
    if (push.worker) push.worker.terminate();
  }
  return push;
}
