// The live model in a Web Worker: fpm-step.js's FpmModel stepped in a loop, pushed by the page.
//
// A module worker: new Worker(new URL("./live-worker.js", import.meta.url), {type: "module"}).
//
// Messages in (postMessage objects, by `type`):
//   load     {model: <parsed JSON export>} | {text: <its JSON text>} | {buffer: <its UTF-8 bytes,
//            an ArrayBuffer (transfer it)>} | {url, headers}: build the model (a URL is fetched
//            here; a 202 is asked again after its Retry-After) and start; damping? "engine" |
//            "kernel" (FpmModel.fromExport's: unset, the export's engine d and dt where it has
//            them).
//   push     {node, force: [fx, fy, fz]}: a constant force on a node, N, until changed
//            (force null or [0, 0, 0] takes it away). A model fitted with fpm.loads "hat" (its
//            export has load_shares) takes a push or drag on a surface node as the fit took a
//            force there: shared over the nodes around it (fpm.runtime.Runtime.applied).
//   drag     {node, target: [x, y, z], stiffness?, maxForce?}: a spring-like force toward the
//            target, k (target - x_node), each step from the node's current position; k defaults
//            to the sum of the node's spring stiffnesses, maxForce (N) to FpmModel.stepForceLimit's
//            (the pull that moves the node half its shortest spring in one step); target null
//            lets go.
//   release  {}: every push and drag let go.
//   reset    {}: back to rest (forces kept).
//   pause / resume {}: stop / start stepping.
//   config   {budgetMs?, frameMs?, realtime?}: per frame, step until budgetMs has passed
//            (default 12 ms of a 16 ms frame); realtime caps the steps at frameMs / dt.
//   step     {count}: exactly `count` steps now, then one frame posted (for tests and benches).
//   recycle  {buffer}: a positions buffer the page is done with, to be filled again.
// Messages out:
//   ready    {nodes, springs, hexahedra, dt, d, damping ("engine" or "kernel"),
//            rest: Float32Array(3 N)}
//   frame    {positions: Float32Array(3 N) (transferred), steps (in all), stepsThisFrame,
//            stepsPerSecond, unbalanced, settled, ms (stepping time of the frame), dragForce (the
//            largest drag's pull in the last step, N)}
//   error    {message}
// Stepping stops by itself, after one last frame, once the model has settled under what is on it
// (or has had no load since the last reset), and starts again with the next push, drag, release
// or reset.
import { FpmModel } from "./fpm-step.js";

let model = null;
let forces = null; // Float64Array(3 N): what the pushes and drags put on the nodes this step
let shares = null; // node -> [nodes, weights] of the export's load_shares ("hat"), or null
const touched = []; // the nodes whose forces this step's applyForces wrote
let handleStiffness = null; // per node: the default drag stiffness
let handleLimit = null; // per node: the default largest drag force (FpmModel.stepForceLimit)
const pushes = new Map(); // node -> [fx, fy, fz]
const drags = new Map(); // node -> {target, stiffness, maxForce}
const pool = []; // positions buffers handed back by the page
let budgetMs = 12;
let frameMs = 16;
let realtime = false;
let paused = false;
let timer = null;
let lastRate = 0;
let dragForce = 0; // the largest drag's |f| in the last step, N
let changed = false; // a push, drag, release or reset since the last step (settled is stale)

function post(message, transfer) {
  self.postMessage(message, transfer || []);
}

function fail(error) {
  post({ type: "error", message: String(error && error.message ? error.message : error) });
}

async function fetchExport(url, headers) {
  for (;;) {
    const response = await fetch(url, { headers: headers || {} });
    if (response.status === 202) {
      const wait = Number(response.headers.get("Retry-After")) || 1;
      await new Promise((resolve) => setTimeout(resolve, 1000 * wait));
      continue;
    }
    if (!response.ok) throw new Error(`${url}: ${response.status} ${response.statusText}`);
    return response.json();
  }
}

// The export's load_shares (a compressed-row table) as node -> [Int32Array, Float64Array].
function readShares(table) {
  if (!table) return null;
  const out = new Map();
  table.nodes.forEach((node, r) => {
    const a = table.indptr[r];
    const b = table.indptr[r + 1];
    const nodes = Int32Array.from(table.indices.slice(a, b));
    out.set(node, [nodes, Float64Array.from(table.weights.slice(a, b))]);
  });
  return out;
}

function load(doc, damping) {
  model = FpmModel.fromExport(doc, { damping });
  forces = new Float64Array(3 * model.nNodes);
  shares = readShares(doc.load_shares);
  touched.length = 0;
  handleStiffness = model.nodeStiffness();
  handleLimit = model.stepForceLimit();
  pushes.clear();
  drags.clear();
  pool.length = 0;
  const rest = Float32Array.from(model.rest);
  post(
    {
      type: "ready",
      nodes: model.nNodes,
      springs: model.nSprings,
      hexahedra: model.nHexahedra,
      dt: model.dt,
      d: model.d,
      damping: model.damping,
      rest,
    },
    [rest.buffer],
  );
}

// Force (f0, f1, f2), N, meant for `node` added to this step's forces: shared over the nodes
// around it as the fit applied it (load_shares), or at the node.
function addForce(node, f0, f1, f2) {
  const row = shares && shares.get(node);
  if (!row) {
    forces[3 * node] += f0;
    forces[3 * node + 1] += f1;
    forces[3 * node + 2] += f2;
    touched.push(node);
    return;
  }
  const [nodes, weights] = row;
  for (let r = 0; r < nodes.length; r++) {
    const k = 3 * nodes[r];
    forces[k] += weights[r] * f0;
    forces[k + 1] += weights[r] * f1;
    forces[k + 2] += weights[r] * f2;
    touched.push(nodes[r]);
  }
}

// The forces of this step, from zero: the pushes, and each drag's pull from the node's current
// position (plus the node's push).
function applyForces() {
  for (const node of touched) forces.fill(0, 3 * node, 3 * node + 3);
  touched.length = 0;
  const x = model.x;
  dragForce = 0;
  for (const [node, p] of pushes) if (!drags.has(node)) addForce(node, p[0], p[1], p[2]);
  for (const [node, d] of drags) {
    const k = 3 * node;
    let f0 = d.stiffness * (d.target[0] - x[k]);
    let f1 = d.stiffness * (d.target[1] - x[k + 1]);
    let f2 = d.stiffness * (d.target[2] - x[k + 2]);
    const size = Math.sqrt(f0 * f0 + f1 * f1 + f2 * f2);
    if (d.maxForce > 0 && size > d.maxForce) {
      const s = d.maxForce / size;
      f0 *= s;
      f1 *= s;
      f2 *= s;
    }
    dragForce = Math.max(dragForce, Math.min(size, d.maxForce > 0 ? d.maxForce : size));
    const p = pushes.get(node);
    addForce(node, f0 + (p ? p[0] : 0), f1 + (p ? p[1] : 0), f2 + (p ? p[2] : 0));
  }
}

function active() {
  return pushes.size > 0 || drags.size > 0;
}

function checkNode(node) {
  if (!Number.isInteger(node) || node < 0 || node >= model.nNodes) {
    throw new Error(`no node ${node} (the model has ${model.nNodes})`);
  }
}

function postFrame(stepsThisFrame, ms) {
  const n3 = 3 * model.nNodes;
  let positions = null;
  while (pool.length && !positions) {
    const buffer = pool.pop();
    if (buffer.byteLength === 4 * n3) positions = new Float32Array(buffer);
  }
  if (!positions) positions = new Float32Array(n3);
  positions.set(model.x);
  if (ms > 0 && stepsThisFrame > 0) lastRate = (1000 * stepsThisFrame) / ms;
  post(
    {
      type: "frame",
      positions,
      steps: model.steps,
      stepsThisFrame,
      stepsPerSecond: lastRate,
      unbalanced: model.unbalanced,
      settled: model.settled,
      ms,
      dragForce,
    },
    [positions.buffer],
  );
}

// Nothing left to step: no force changed since the last step, and the model is settled (under
// constant pushes, or a drag whose pull has settled too), or has had no load since its reset
// (and no gravity), so it is at rest.
function idle() {
  if (changed) return false;
  if (model.settled) return true;
  const g = model.gravity;
  return !active() && model.loadScale === 0 && g[0] === 0 && g[1] === 0 && g[2] === 0;
}

function frame() {
  timer = null;
  if (!model || paused) return;
  if (idle()) return postFrame(0, 0); // the state as it is, once
  const start = performance.now();
  const cap = realtime ? Math.max(1, Math.round(frameMs / 1000 / model.dt)) : Infinity;
  let count = 0;
  do {
    applyForces();
    model.step(forces);
    count += 1;
  } while (count < cap && performance.now() - start < budgetMs);
  changed = false;
  const ms = performance.now() - start;
  postFrame(count, ms);
  if (idle()) return; // at rest: wait for the next message
  schedule(Math.max(0, frameMs - ms));
}

function schedule(delay = 0) {
  if (timer === null && model && !paused) timer = setTimeout(frame, delay);
}

const handlers = {
  async load(m) {
    if (m.model) load(m.model, m.damping);
    else if (typeof m.text === "string") load(JSON.parse(m.text), m.damping);
    else if (m.buffer instanceof ArrayBuffer) {
      load(JSON.parse(new TextDecoder().decode(m.buffer)), m.damping);
    } else if (m.url) load(await fetchExport(m.url, m.headers), m.damping);
    else throw new Error("load: give model, text or url");
  },
  push(m) {
    checkNode(m.node);
    changed = true;
    const zero = !m.force || m.force.every((c) => c === 0);
    if (zero) pushes.delete(m.node);
    else pushes.set(m.node, m.force.map(Number));
  },
  drag(m) {
    checkNode(m.node);
    changed = true;
    if (!m.target) {
      drags.delete(m.node);
      return;
    }
    drags.set(m.node, {
      target: m.target.map(Number),
      stiffness: m.stiffness > 0 ? m.stiffness : handleStiffness[m.node],
      maxForce: m.maxForce > 0 ? m.maxForce : handleLimit[m.node],
    });
  },
  release() {
    changed = true;
    pushes.clear();
    drags.clear();
  },
  reset() {
    changed = true;
    model.reset();
  },
  pause() {
    paused = true;
    if (timer !== null) clearTimeout(timer);
    timer = null;
  },
  resume() {
    paused = false;
  },
  config(m) {
    if (m.budgetMs > 0) budgetMs = m.budgetMs;
    if (m.frameMs > 0) frameMs = m.frameMs;
    if (typeof m.realtime === "boolean") realtime = m.realtime;
  },
  step(m) {
    const start = performance.now();
    const count = Math.max(0, Math.floor(m.count || 1));
    for (let n = 0; n < count; n++) {
      applyForces();
      model.step(forces);
    }
    if (count > 0) changed = false;
    postFrame(count, performance.now() - start);
  },
  recycle(m) {
    if (m.buffer instanceof ArrayBuffer) pool.push(m.buffer);
  },
};

self.onmessage = async (event) => {
  const m = event.data || {};
  const handler = handlers[m.type];
  if (!handler) return fail(`unknown message type ${m.type}`);
  if (m.type !== "load" && m.type !== "config" && !model) return fail("no model loaded yet");
  try {
    await handler(m);
  } catch (error) {
    return fail(error);
  }
  if (m.type !== "recycle" && m.type !== "step") schedule();
};
