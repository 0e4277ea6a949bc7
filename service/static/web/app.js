// The web view of the FPM calibration service: plain JavaScript, no library, no CDN.
//
// Routes live in the URL's fragment: #/ (calibrations), #/calibrations/<id> (one calibration),
// #/parameter-sets, #/parameter-sets/<id> and #/parameter-sets/<id>/3d (its 3D view: the module
// view3d.js with three.js, loaded only there). Everything shown comes from the /v1 endpoints,
// polled while something runs; charts are inline SVG drawn here. When the service answers 401
// (API keys are set) the page asks for a key, keeps it in this tab's session storage and sends
// it as X-API-Key. Text from the service is always inserted as text, never as HTML.
"use strict";

(() => {
  const KEY_STORE = "fpm-api-key";
  const COLORS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd",
    "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"];
  const ACTIVE = new Set(["queued", "running"]);
  const POLL_ACTIVE_MS = 2000;
  const POLL_IDLE_MS = 10000;
  const POLL_PROFILE_MS = 1000;
  const PHASE_NAMES = {
    queued: "queued", fem: "FEM reference", annealing: "annealing", damping: "damping",
    finalize: "finalize", done: "done",
  };

  // ---- DOM helpers ---------------------------------------------------------------------------

  function append(node, children) {
    for (const child of children.flat(Infinity)) {
      if (child === null || child === undefined || child === false) continue;
      node.append(child instanceof Node ? child : document.createTextNode(String(child)));
    }
    return node;
  }

  function setAttrs(node, attrs) {
    for (const [name, value] of Object.entries(attrs || {})) {
      if (value === null || value === undefined || value === false) continue;
      if (name.startsWith("on")) node.addEventListener(name.slice(2), value);
      else if (name === "style") node.style.cssText = String(value); // CSP: no style attributes
      else node.setAttribute(name, value === true ? "" : String(value));
    }
    return node;
  }

  function el(tag, attrs, ...children) {
    return append(setAttrs(document.createElement(tag), attrs), children);
  }

  const SVG_NS = "http://www.w3.org/2000/svg";
  function svg(tag, attrs, ...children) {
    return append(setAttrs(document.createElementNS(SVG_NS, tag), attrs), children);
  }

  const view = () => document.getElementById("view");
  const show = (...nodes) => view().replaceChildren(...nodes.flat().filter((n) => n !== null)); // null: a panel with nothing to show
  const enc = encodeURIComponent;

  // ---- Formatting ----------------------------------------------------------------------------

  function num(x, digits = 4) {
    if (x === null || x === undefined || !Number.isFinite(Number(x))) return "–";
    const v = Number(x);
    if (v !== 0 && (Math.abs(v) >= 1e6 || Math.abs(v) < 1e-3)) return v.toExponential(digits - 1);
    return String(Number(v.toPrecision(digits)));
  }

  const pct = (x, digits = 2) => (Number.isFinite(x) ? `${x.toFixed(digits)}%` : "–");
  const mm = (metres, digits = 4) => `${num(metres * 1e3, digits)} mm`;

  function toDate(t) {
    if (t === null || t === undefined || t === "") return null;
    const d = typeof t === "number" ? new Date(t * 1000) : new Date(t);
    return Number.isNaN(d.getTime()) ? null : d;
  }

  function when(t) {
    const d = toDate(t);
    return d ? `${d.toISOString().slice(0, 19).replace("T", " ")} UTC` : "–";
  }

  function seconds(s) {
    if (s === null || s === undefined || !Number.isFinite(s)) return "–";
    if (s < 60) return `${s.toFixed(s < 10 ? 2 : 1)} s`;
    const m = Math.floor(s / 60);
    return m < 60 ? `${m} min ${Math.round(s - 60 * m)} s` : `${(s / 3600).toFixed(2)} h`;
  }

  const pick = (obj, ...names) => {
    for (const name of names) if (obj && obj[name] !== undefined && obj[name] !== null) return obj[name];
    return null;
  };
  const damping = (r) => pick(r, "damping", "d");

  function statusBadge(status) {
    return el("span", { class: `status status-${status}`, "data-status": status }, status);
  }

  function bar(fraction, title) {
    const f = Math.max(0, Math.min(1, Number.isFinite(fraction) ? fraction : 0));
    return el("div", { class: "bar", title }, el("span", { style: `width:${(100 * f).toFixed(1)}%` }));
  }

  function stiffnessText(stiffness, k) {
    const entries = Object.entries(stiffness || {});
    if (!entries.length) return `${num(k)} N/m`;
    const values = new Set(entries.map(([, v]) => v));
    if (values.size === 1) return `${num(entries[0][1])} N/m (one k: ${entries.map(([f]) => f).join(", ")})`;
    return entries.map(([family, v]) => `${family} ${num(v)}`).join(", ") + " N/m";
  }

  // ---- The API, with the key -----------------------------------------------------------------

  class ApiError extends Error {
    constructor(status, body) {
      const detail = body && (body.detail || body.title);
      super(detail ? `${status}: ${detail}` : `HTTP ${status}`);
      this.status = status;
      this.body = body;
    }
  }

  let apiKey = sessionStorage.getItem(KEY_STORE) || "";
  let keyWaiter = null;

  function askKey(reason) {
    if (keyWaiter) return keyWaiter.promise;
    const form = document.getElementById("key-form");
    document.getElementById("key-reason").textContent = reason;
    form.hidden = false;
    const input = document.getElementById("key-input");
    input.value = "";
    input.focus();
    let resolve, reject;
    const promise = new Promise((res, rej) => { resolve = res; reject = rej; });
    keyWaiter = { promise, resolve, reject };
    return promise;
  }

  function keyGiven(event) {
    event.preventDefault();
    apiKey = document.getElementById("key-input").value.trim();
    sessionStorage.setItem(KEY_STORE, apiKey);
    document.getElementById("key-form").hidden = true;
    showKeyStatus();
    const waiter = keyWaiter;
    keyWaiter = null;
    if (waiter) waiter.resolve();
    else route();
  }

  function keyDismissed() {
    document.getElementById("key-form").hidden = true;
    const waiter = keyWaiter;
    keyWaiter = null;
    if (waiter) waiter.reject(new ApiError(401, { detail: "no API key given" }));
  }

  function showKeyStatus() {
    const box = document.getElementById("key-status");
    if (apiKey) {
      box.replaceChildren("API key: set", el("button", {
        type: "button",
        onclick: () => { apiKey = ""; sessionStorage.removeItem(KEY_STORE); showKeyStatus(); route(); },
      }, "Forget"));
    } else {
      box.replaceChildren(el("button", {
        type: "button", onclick: () => askKey("Give the service's API key (X-API-Key)."),
      }, "Set API key"));
    }
  }

  async function jsonBody(response) {
    try { return await response.json(); } catch (e) { return null; }
  }

  // One request with the API key (a 401 asks for the key and tries again); the response when
  // its status is below 400 (202 included), else an ApiError.
  async function request(method, path, accept) {
    for (let attempt = 0; attempt < 5; attempt++) {
      const headers = { Accept: accept };
      if (apiKey) headers["X-API-Key"] = apiKey;
      const response = await fetch(path, { method, headers });
      if (response.status === 401) {
        const why = apiKey ? "That API key was refused: give another."
          : method === "DELETE" ? "Cancelling needs the service's API key (X-API-Key)."
            : "This service needs an API key (X-API-Key) for its /v1 routes.";
        await askKey(why);
        continue;
      }
      if (!response.ok) throw new ApiError(response.status, await jsonBody(response));
      return response;
    }
    throw new ApiError(401, { detail: "no accepted API key" });
  }

  async function api(method, path) {
    const response = await request(method, path, "application/json");
    return { status: response.status, body: await jsonBody(response) };
  }

  function errorText(error) {
    return error instanceof ApiError ? error.message : `cannot reach the service (${error.message || error})`;
  }

  function errorPanel(error, what) {
    const text = errorText(error);
    return el("div", { class: "panel" }, el("p", { class: "error" }, what ? `${what}: ${text}` : text));
  }

  // ---- Routing and polling -------------------------------------------------------------------

  let viewToken = 0;
  let timer = null;

  function route() {
    viewToken += 1;
    clearTimeout(timer);
    if (view3d) { view3d.dispose(); view3d = null; }
    const token = viewToken;
    const parts = location.hash.replace(/^#\/?/, "").split("/").map(decodeURIComponent);
    const section = parts[0] === "parameter-sets" ? "parameter-sets" : "calibrations";
    for (const link of document.querySelectorAll("header nav a")) {
      link.classList.toggle("current", link.dataset.nav === section);
    }
    if (parts[0] === "calibrations" && parts[1]) calibrationView(parts[1], token);
    else if (parts[0] === "parameter-sets" && parts[1] && parts[2] === "3d") view3dPage(parts[1], token);
    else if (parts[0] === "parameter-sets" && parts[1]) parameterSetView(parts[1], token);
    else if (parts[0] === "parameter-sets") parameterSetsView(token);
    else listView(token);
  }

  const alive = (token) => token === viewToken;

  function later(token, ms, fn) {
    if (!alive(token)) return;
    clearTimeout(timer);
    timer = setTimeout(() => { if (alive(token)) fn(); }, ms);
  }

  // ---- Cancel --------------------------------------------------------------------------------

  function cancelButton(calibration, after) {
    const box = el("span", { class: "cancel" });
    const ask = el("button", {
      type: "button", class: "danger", "data-action": "cancel",
      onclick: () => box.replaceChildren(
        "Cancel this calibration? ",
        el("button", { type: "button", class: "danger confirm", "data-action": "confirm-cancel", onclick: confirm }, "Yes, cancel"),
        " ",
        el("button", { type: "button", onclick: () => box.replaceChildren(ask) }, "No"),
      ),
    }, "Cancel");
    async function confirm() {
      box.replaceChildren(el("span", { class: "muted" }, "canceling…"));
      try {
        await api("DELETE", `v1/calibrations/${enc(calibration.id)}`);
      } catch (error) {
        box.replaceChildren(el("span", { class: "error" }, error.message), " ", ask);
        return;
      }
      after();
    }
    box.append(ask);
    return box;
  }

  // ---- Calibrations --------------------------------------------------------------------------

  const details = new Map(); // id -> the latest GET /v1/calibrations/{id}
  let listFilter = "";

  function progressCell(c) {
    const p = c.progress || {};
    const parts = [];
    if (p.total_iterations) {
      parts.push(bar(p.iterations / p.total_iterations, "annealing moves, all chains"),
        el("div", { class: "muted" }, `${p.iterations} / ${p.total_iterations} moves`));
    }
    if (ACTIVE.has(c.status)) {
      for (const chain of p.chains || []) {
        parts.push(el("div", { class: "muted", "data-chain": chain.chain },
          `chain ${chain.chain}: ${chain.move}/${chain.moves}, best ${num(chain.best_cost)}`));
      }
      if (p.damping) {
        parts.push(el("div", { class: "muted" },
          `damping: ${p.damping.runs} d tried, best d ${num(p.damping.best_d)} N s/m`));
      }
    }
    return parts;
  }

  function listRow(summary) {
    const c = details.get(summary.id);
    const status = c ? c.status : summary.status;
    const result = c && c.result;
    return el("tr", { "data-id": summary.id },
      el("td", null, el("a", { href: `#/calibrations/${enc(summary.id)}` }, summary.name || "(unnamed)"),
        el("div", { class: "muted nowrap" }, summary.id)),
      el("td", null, statusBadge(status)),
      el("td", null, c ? c.progress.stage : "", c && c.error ? el("div", { class: "error" }, c.error) : null),
      el("td", null, c ? progressCell(c) : null),
      el("td", { class: "num" }, c ? num(c.progress.best_cost) : "–"),
      el("td", { class: "num headline" }, result
        ? result.relative_discrepancy.map((v) => pct(v)).join(" / ") : "–"),
      el("td", null, when(summary.created)),
      el("td", null, ACTIVE.has(status) ? cancelButton(summary, () => listView(viewToken)) : null),
    );
  }

  async function listView(token) {
    let page;
    const query = `v1/calibrations?limit=50${listFilter ? `&status=${enc(listFilter)}` : ""}`;
    try {
      page = (await api("GET", query)).body;
    } catch (error) {
      if (!alive(token)) return;
      show(el("h2", null, "Calibrations"), errorPanel(error));
      later(token, POLL_IDLE_MS, () => listView(token));
      return;
    }
    const stale = page.items.filter((i) => ACTIVE.has(i.status) || !details.has(i.id)
      || details.get(i.id).status !== i.status);
    await Promise.all(stale.map(async (i) => {
      try { details.set(i.id, (await api("GET", `v1/calibrations/${enc(i.id)}`)).body); } catch (e) { /* shown without */ }
    }));
    let usage = [];
    try { usage = (await api("GET", "v1/health")).body.keys || []; } catch (e) { /* shown without */ }
    if (!alive(token)) return;
    const filter = el("select", {
      onchange: (event) => { listFilter = event.target.value; route(); },
    }, ["", "queued", "running", "succeeded", "failed", "canceled"].map((s) =>
      el("option", { value: s, selected: s === listFilter }, s || "any status")));
    const active = page.items.some((i) => ACTIVE.has(i.status));
    show(
      el("h2", null, "Calibrations"),
      el("div", { class: "toolbar" }, el("label", null, "Status ", filter),
        el("span", { class: "muted" }, `${page.items.length} of ${page.total}, newest first`,
          active ? " · live: updated every 2 s" : "")),
      usage.length ? el("p", { class: "muted", id: "key-usage" }, "In flight per API key (a hash of the key): ",
        usage.map((u) => `${u.owner} ${u.active} calibrations, ${u.nodes_in_flight} nodes`).join(" · ")) : null,
      page.items.length ? el("table", { id: "calibrations" },
        el("thead", null, el("tr", null,
          ["Calibration", "Status", "Stage", "Progress", "Best cost", "Relative discrepancy per load case",
            "Created", ""].map((h, i) => el("th", { class: i === 4 || i === 5 ? "num" : null }, h)))),
        el("tbody", null, page.items.map(listRow)))
        : el("p", { class: "muted" }, "No calibration yet: submit a spec with POST /v1/calibrations, fpm-client submit or the SDK."),
    );
    later(token, active ? POLL_ACTIVE_MS : POLL_IDLE_MS, () => listView(token));
  }

  // ---- One calibration -----------------------------------------------------------------------

  const caseNames = new Map(); // FEM reference id -> load case names
  const traces = new Map(); // calibration id -> [{t, costs: {chain: best}}], while watched
  const profiles = new Map(); // calibration id -> ready profile data

  async function loadCaseNames(femId) {
    if (!caseNames.has(femId)) {
      try {
        const fem = (await api("GET", `v1/fem-references/${enc(femId)}?arrays=false`)).body;
        if (fem.load_cases) caseNames.set(femId, fem.load_cases);
      } catch (e) { return null; }
    }
    return caseNames.get(femId) || null;
  }

  function stagesStrip(p) {
    const current = p.stages.indexOf(p.phase);
    return el("div", { class: "stages" }, p.stages.map((phase, i) => el("span", {
      class: p.phase === "done" || i < current ? "done" : i === current ? "now" : null,
    }, PHASE_NAMES[phase] || phase)));
  }

  function progressPanel(c) {
    const p = c.progress;
    const rows = (p.chains || []).map((chain) => el("tr", { "data-chain": chain.chain },
      el("td", null, `chain ${chain.chain}`),
      el("td", null, bar(chain.moves ? chain.move / chain.moves : 0)),
      el("td", { class: "num" }, `${chain.move} / ${chain.moves}`),
      el("td", { class: "num" }, num(chain.temperature)),
      el("td", { class: "num" }, num(chain.best_cost))));
    const d = p.damping;
    return el("div", { class: "panel", id: "progress" },
      el("h3", null, "Progress"),
      el("p", null, el("strong", null, p.stage), ` · method ${p.method}`,
        p.total_iterations ? ` · ${p.iterations} / ${p.total_iterations} annealing moves` : "",
        p.best_cost !== null ? ` · best cost ${num(p.best_cost)}` : ""),
      stagesStrip(p),
      rows.length ? el("table", null,
        el("thead", null, el("tr", null, ["Chain", "", "Moves", "Temperature", "Best cost (normalised)"]
          .map((h, i) => el("th", { class: i > 1 ? "num" : null }, h)))),
        el("tbody", null, rows)) : null,
      d ? el("p", { id: "damping" }, `Damping stage: ${d.step || "starting"}, ${d.runs} d tried`,
        pick(d, "last_d", "d") !== null ? `, last d ${num(pick(d, "last_d", "d"))} N s/m (${d.total_steps === null ? "did not settle" : `${d.total_steps} steps`})` : "",
        d.best_d !== null ? `, fastest so far d ${num(d.best_d)} N s/m (${d.best_total_steps} steps)` : "") : null,
      liveChart(c));
  }

  function recordTrace(c) {
    if (!ACTIVE.has(c.status)) return;
    const points = traces.get(c.id) || [];
    const costs = {};
    for (const chain of c.progress.chains || []) if (chain.best_cost !== null) costs[chain.chain] = chain.best_cost;
    points.push({ t: performance.now() / 1000, costs });
    traces.set(c.id, points.slice(-600));
  }

  function liveChart(c) {
    const points = traces.get(c.id);
    if (!ACTIVE.has(c.status) || !points || points.length < 2) return null;
    const chains = [...new Set(points.flatMap((p) => Object.keys(p.costs)))].sort((a, b) => a - b);
    if (!chains.length) return null;
    const t0 = points[0].t;
    return lineChart({
      title: "best cost per chain, live (since this page opened)",
      xLabel: "seconds", yLabel: "best cost / reference cost", logY: true, height: 200,
      series: chains.map((chain, i) => ({
        label: `chain ${chain}`, color: COLORS[i % COLORS.length],
        x: points.map((p) => p.t - t0), y: points.map((p) => p.costs[chain] ?? NaN),
      })),
    });
  }

  function verdictCard(v) {
    // The verdict on the fit (fpm.fitting.verdict): the grade first, its summary, the floor
    // the model family reaches and its page, the likely causes each with its action.
    if (!v) return null;
    return el("div", { class: `verdict verdict-${v.grade}`, id: "verdict", "data-grade": v.grade },
      el("p", null, el("strong", { class: "grade" }, v.grade.toUpperCase()), " ", v.summary.slice(v.grade.length + 2)),
      el("p", { class: "muted" }, `Floor: ${v.floor.what} (${v.floor.source}).`),
      v.causes.length ? el("ul", { class: "causes" }, v.causes.map((c) => el("li", { "data-cause": c.cause },
        el("strong", null, c.cause), `: ${c.detail}. `, el("em", null, "Action: "), c.action))) : null);
  }

  const ratio = (x) => (Number.isFinite(x) ? x.toFixed(3) : "–");

  function fitPanel(c, names) {
    const r = c.result;
    const cases = r.relative_discrepancy.map((_, j) => (names && names[j]) || `load case ${j + 1}`);
    return el("div", { class: "panel", id: "fit" },
      el("h3", null, "Fit per load case"),
      el("table", null,
        el("thead", null, el("tr", null, ["Load case", "Relative discrepancy", "Loaded nodes", "% of h", "Settle steps", "Compliance"]
          .map((h, i) => el("th", { class: i ? "num" : null }, h)))),
        el("tbody", null, cases.map((name, j) => el("tr", { "data-case": j },
          el("td", null, name),
          el("td", { class: "num headline relative" }, pct(r.relative_discrepancy[j])),
          el("td", { class: "num" }, pct(r.loaded_discrepancy[j])),
          el("td", { class: "num" }, pct(r.discrepancy_h[j])),
          el("td", { class: "num" }, r.settle_steps[j] ?? "–"),
          el("td", { class: "num compliance" }, ratio((r.compliance_ratio || [])[j])))))),
      barChart(cases.map((name, j) => ({ label: name, value: r.relative_discrepancy[j], color: COLORS[j % COLORS.length] })),
        "relative discrepancy, % (100 Σ|p−q| / Σ|q|, all nodes)"),
      el("p", { class: "muted" }, "Relative: summed nodal error over the FEM's summed displacement (0% perfect, ",
        "100% no better than not moving). Loaded nodes: the same at the loaded nodes. % of h: mean nodal ",
        "error over the lattice spacing h (the paper's unit), read beside the relative figure. ",
        "Compliance: the work of the load on the model over that on the reference (1.0: a probe feels ",
        "the reference's stiffness; 1.5: 1.5 times too soft)."),
      validationTable(r),
      referenceError(r));
  }

  function fieldPanel(r) {
    // fpm.stiffness "field": the four parameters and the per-cell field side by side (fitted,
    // never fitted, left out), and the cross-validation error at each smoothness weight tried.
    const f = r.field;
    if (!f) return null;
    const joined = (xs) => (xs || []).length ? xs.map((x) => pct(x)).join(" / ") : "–";
    const row = (label, m, returned) => el("tr", { "data-model": label },
      el("td", null, label, returned ? " (returned)" : ""),
      el("td", { class: "num" }, joined(m.relative_discrepancy)),
      el("td", { class: "num headline" }, joined(m.validation_relative_discrepancy)),
      el("td", { class: "num" }, pct(m.cv_error)));
    return el("div", { class: "panel", id: "field" },
      el("h3", null, "Stiffness field against the four parameters"),
      el("table", null,
        el("thead", null, el("tr", null, ["Model", "Fit", "Validation (never fitted)", "Left out (CV)"]
          .map((h, i) => el("th", { class: i ? "num" : null }, h)))),
        el("tbody", null, row("four parameters", f.four_parameter, !f.returned), row("field", f.field, f.returned))),
      el("table", { id: "field-cv" },
        el("thead", null, el("tr", null, ["Smoothness weight", "Left-out relative discrepancy"]
          .map((h, i) => el("th", { class: i ? "num" : null }, h)))),
        el("tbody", null, f.cv_weights.map((w, i) => el("tr", { class: w === f.smoothness_weight ? "chosen" : null },
          el("td", null, num(w, 3), w === f.smoothness_weight ? " (chosen)" : ""),
          el("td", { class: "num" }, pct(f.cv_error[i])))))),
      el("p", { class: "muted" }, "Left out: each force pattern's relative discrepancy when fitted without it, ",
        "averaged; the field is returned only when it beats the four parameters there."));
  }

  function referenceError(r) {
    // The reference's own estimated error (reference.refine): the fit cannot be closer than it.
    const e = r.reference_error;
    if (!e) return null;
    const v = r.validation_reference_error || [];
    const high = [...e, ...v].some((x) => x > 5);
    const text = `Reference's estimated error: ${e.map((x) => pct(x)).join(" / ")}`
      + (v.length ? `; validation ${v.map((x) => pct(x)).join(" / ")}` : "")
      + (r.reference_refinements ? ` (the change from its last refinement, ${r.reference_refinements} in all)`
        : " (its change under one refinement, the forces spread)")
      + (high ? ": above 5%, the reference does not resolve that load" : ".");
    return high ? el("ul", { class: "warnings", id: "reference-error" }, el("li", null, text))
      : el("p", { class: "muted", id: "reference-error" }, text);
  }

  function validationTable(r) {
    const v = r.validation_relative_discrepancy || [];
    if (!v.length) return null;
    const names = r.validation_cases || [];
    return el("div", { id: "validation" },
      el("h3", null, "Validation cases (never fitted: the honest figure)"),
      el("table", null,
        el("thead", null, el("tr", null, ["Validation case", "Relative discrepancy", "% of h", "Compliance"]
          .map((h, i) => el("th", { class: i ? "num" : null }, h)))),
        el("tbody", null, v.map((value, j) => el("tr", { "data-validation": j },
          el("td", null, names[j] || `case ${j + 1}`),
          el("td", { class: "num headline validation" }, pct(value)),
          el("td", { class: "num" }, pct((r.validation_discrepancy_h || [])[j])),
          el("td", { class: "num compliance" }, ratio((r.validation_compliance_ratio || [])[j])))))));
  }

  function parametersPanel(c) {
    const r = c.result;
    const mass = r.node_mass || {};
    const facts = [
      ["method", r.method],
      ["model", r.stiffness_mode || "single"],
      ["stiffness k", stiffnessText(r.stiffness, r.k)],
      ...(r.volume_stiffness !== null && r.volume_stiffness !== undefined
        ? [["volume stiffness kappa", `${num(r.volume_stiffness)} Pa`]] : []),
      ...(r.dt ? [["dt", `${num(r.dt * 1e3)} ms`]] : []),
      ["damping d", `${num(damping(r))} N s/m${r.d_min !== null && r.d_min !== undefined ? ` (d_min ${num(r.d_min)})` : ""}`],
      ["depth", `${r.depth} layers (the deepest perturbed list: ${r.full_depth})`],
      ["h", mm(r.h)],
      ["node mass", `min ${num(mass.min * 1e3)} g, max ${num(mass.max * 1e3)} g, total ${num(mass.total)} kg`],
      ["cost (Eq. 2)", `${num(r.cost)} m dynamic, ${num(r.static_cost)} m static`],
      ["settled", r.settled ? "every load case" : "no"],
      ["evaluations", `${r.evaluations} (stiffness search), ${r.damping_runs} damping runs`],
      ["wall time", Object.entries(r.seconds || {}).map(([k, v]) => `${k} ${seconds(v)}`).join(", ")],
    ];
    return el("div", { class: "panel", id: "parameters" },
      el("h3", null, "Fitted parameters"),
      el("dl", { class: "facts" }, facts.map(([k, v]) => [el("dt", null, k), el("dd", null, v)])),
      c.parameter_set_id ? el("p", null, "Parameter set ",
        el("a", { href: `#/parameter-sets/${enc(c.parameter_set_id)}` }, c.parameter_set_id), " · ",
        view3dLink(c.parameter_set_id)) : null,
      r.warnings && r.warnings.length ? el("ul", { class: "warnings" }, r.warnings.map((w) => el("li", null, w))) : null);
  }

  function historyPanel(c) {
    const history = c.result.history || [];
    let best = Infinity;
    const bestSoFar = history.map((v) => (best = Math.min(best, v)));
    const x = history.map((_, i) => i + 1);
    return el("div", { class: "panel", id: "history" },
      el("h3", null, "Cost history of the winning chain"),
      history.length ? lineChart({
        xLabel: "annealing move", yLabel: "cost / reference cost", logY: true,
        series: [
          { label: "current state", color: COLORS[0], x, y: history },
          { label: "best so far", color: COLORS[1], x, y: bestSoFar },
        ],
      }) : el("p", { class: "muted" }, "No history stored."));
  }

  function profilePanel(c, token) {
    const box = el("div", { id: "profile-chart" }, el("p", { class: "muted" }, "Loading the profiles…"));
    const panel = el("div", { class: "panel", id: "profile" },
      el("h3", null, "FPM and FEM displacement profiles"), box);
    const draw = (data) => box.replaceChildren(profileChart(data));
    if (profiles.has(c.id)) draw(profiles.get(c.id));
    else {
      const poll = async () => {
        let answer;
        try {
          answer = (await api("GET", `v1/calibrations/${enc(c.id)}/profile`)).body;
        } catch (error) {
          if (alive(token)) box.replaceChildren(errorPanel(error, "profiles"));
          return;
        }
        if (!alive(token)) return;
        if (answer.status === "ready") { profiles.set(c.id, answer); draw(answer); }
        else if (answer.status === "failed") box.replaceChildren(el("p", { class: "error" }, answer.error));
        else {
          box.replaceChildren(el("p", { class: "muted" }, "A worker is computing the FPM run at the fitted parameters…"));
          later(token, POLL_PROFILE_MS, poll);
        }
      };
      poll();
    }
    return panel;
  }

  function profileChart(data) {
    const axes = new Set(data.load_cases.map((lc) => lc.axis));
    const series = data.load_cases.flatMap((lc, j) => {
      const color = COLORS[j % COLORS.length];
      const x = lc.position.map((v) => v * 1e3);
      return [
        { label: `FEM ${lc.name} (along ${lc.axis})`, color, x, y: lc.fem.map((v) => v * 1e3) },
        { label: `FPM: ${pct(lc.relative_discrepancy)} relative, ${pct(lc.discrepancy_h)} of h`,
          color, dash: true, markers: true, x, y: lc.fpm.map((v) => v * 1e3) },
      ];
    });
    return lineChart({
      xLabel: axes.size === 1 ? `${[...axes][0]} through the loaded node, mm`
        : "position along each load case's line through its loaded node, mm",
      yLabel: "displacement magnitude, mm", series, yFromZero: true,
    });
  }

  async function calibrationView(id, token) {
    let c;
    try {
      c = (await api("GET", `v1/calibrations/${enc(id)}`)).body;
    } catch (error) {
      if (!alive(token)) return;
      show(el("h2", null, "Calibration ", id), errorPanel(error));
      if (!(error instanceof ApiError && error.status === 404)) later(token, POLL_IDLE_MS, () => calibrationView(id, token));
      return;
    }
    details.set(c.id, c);
    recordTrace(c);
    const names = c.result ? await loadCaseNames(c.fem_reference_id) : null;
    if (!alive(token)) return;
    const t = c.timings || {};
    const head = el("div", { class: "panel", id: "summary" },
      el("h2", null, c.name || "(unnamed)", " ", statusBadge(c.status)),
      el("dl", { class: "facts" },
        el("dt", null, "id"), el("dd", null, c.id),
        el("dt", null, "created"), el("dd", null, when(t.created)),
        el("dt", null, "started"), el("dd", null, when(t.started)),
        el("dt", null, "finished"), el("dd", null, when(t.finished)),
        el("dt", null, "queued, running"), el("dd", null, `${seconds(t.queued_seconds)}, ${seconds(t.running_seconds)}`),
        el("dt", null, "FEM reference"), el("dd", null, c.fem_reference_id.slice(0, 16), "…", c.fem_cached ? " (was stored)" : "")),
      c.error ? el("p", { class: "error" }, c.error) : null,
      c.result ? verdictCard(c.result.verdict) : null,
      ACTIVE.has(c.status) ? el("p", null, cancelButton(c, () => calibrationView(id, viewToken))) : null);
    const panels = [el("p", null, el("a", { href: "#/" }, "← all calibrations")), head, progressPanel(c)];
    if (c.result) {
      panels.push(el("div", { class: "grid" }, fitPanel(c, names), parametersPanel(c)),
        el("div", { class: "grid" }, profilePanel(c, token), historyPanel(c)), fieldPanel(c.result),
        timelinePanel(c.result));
    }
    show(panels);
    if (ACTIVE.has(c.status)) later(token, POLL_ACTIVE_MS, () => calibrationView(id, token));
  }

  // ---- Parameter sets ------------------------------------------------------------------------

  function materialText(m) {
    return `E ${num(m.youngs_modulus)} Pa, ν ${num(m.poisson_ratio)}, ρ ${num(m.density)} kg/m³`;
  }

  function materialCell(m) {
    return [el("div", { class: "nowrap" }, `E ${num(m.youngs_modulus)} Pa`),
      el("div", { class: "nowrap" }, `ν ${num(m.poisson_ratio)}, ρ ${num(m.density)} kg/m³`)];
  }

  function geometryText(g) {
    const size = g.size ? `, ${g.size.map((s) => num(s * 1e3)).join(" × ")} mm` : "";
    return `${g.type}${g.connectivity ? ` (${g.connectivity})` : ""}${size}, ${g.nodes} nodes`;
  }

  function parameterSetRow(ps) {
    const prov = ps.provenance || {};
    return el("tr", { "data-id": ps.id },
      el("td", null, el("a", { href: `#/parameter-sets/${enc(ps.id)}` }, ps.name), el("div", { class: "muted nowrap" }, ps.id),
        el("div", null, view3dLink(ps.id))),
      el("td", null, materialCell(ps.material)),
      el("td", null, geometryText(ps.geometry)),
      el("td", { class: "num" }, mm(ps.geometry.h)),
      el("td", null, stiffnessText(ps.stiffness, ps.k), el("div", { class: "muted" }, ps.stiffness_mode)),
      el("td", null, `${num(damping(ps))} N s/m at dt ${num(ps.dt * 1e3)} ms`,
        ps.d_min !== null && ps.d_min !== undefined ? el("div", { class: "muted" }, `d_min ${num(ps.d_min)}`) : null),
      el("td", { class: "num" }, ps.depth),
      el("td", { class: "num headline" }, ps.relative_discrepancy.map((v) => pct(v)).join(" / "),
        el("div", { class: "muted" }, `% of h: ${ps.discrepancy_h.map((v) => pct(v)).join(" / ")}`)),
      el("td", null, prov.calibration_id ? el("a", { href: `#/calibrations/${enc(prov.calibration_id)}` }, prov.calibration_id) : "–",
        el("div", { class: "muted" }, prov.method || "")),
      el("td", null, when(ps.created)));
  }

  function parameterSetTable(items) {
    return el("table", { id: "parameter-sets" },
      el("thead", null, el("tr", null, ["Parameter set", "Material", "Geometry", "h", "Stiffness per family",
        "Damping", "Depth", "Relative discrepancy per load case", "Calibration", "Created"]
        .map((h) => el("th", null, h)))),
      el("tbody", null, items.map(parameterSetRow)));
  }

  async function parameterSetsView(token) {
    let page;
    try {
      page = (await api("GET", "v1/parameter-sets")).body;
    } catch (error) {
      if (alive(token)) show(el("h2", null, "Parameter sets"), errorPanel(error));
      return;
    }
    if (!alive(token)) return;
    show(el("h2", null, "Parameter sets"),
      el("p", { class: "muted" }, `${page.total} stored, newest first. k depends on the lattice spacing h: `,
        "use a set only on the mesh it was fitted on, and d only with its dt."),
      page.items.length ? parameterSetTable(page.items) : el("p", { class: "muted" }, "None stored yet."));
    later(token, POLL_IDLE_MS, () => parameterSetsView(token));
  }

  async function parameterSetView(id, token) {
    let ps;
    try {
      ps = (await api("GET", `v1/parameter-sets/${enc(id)}`)).body;
    } catch (error) {
      if (alive(token)) show(el("h2", null, "Parameter set ", id), errorPanel(error));
      return;
    }
    if (!alive(token)) return;
    const facts = [
      ["id", ps.id], ["material", materialText(ps.material)], ["geometry", geometryText(ps.geometry)],
      ["h", mm(ps.geometry.h)], ["stiffness", `${stiffnessText(ps.stiffness, ps.k)} (${ps.stiffness_mode})`],
      ["stiffness scale", (ps.stiffness_scale || []).map((s) => num(s)).join(", ")],
      ["damping d", `${num(damping(ps))} N s/m${ps.d_min !== null && ps.d_min !== undefined ? ` (d_min ${num(ps.d_min)})` : ""}`],
      ["dt", `${num(ps.dt * 1e3)} ms`], ["depth", ps.depth],
      ...(ps.volume_stiffness !== null && ps.volume_stiffness !== undefined
        ? [["volume stiffness kappa", `${num(ps.volume_stiffness)} Pa`]] : []),
      ["relative discrepancy", ps.relative_discrepancy.map((v) => pct(v)).join(" / ")],
      ...((ps.validation_relative_discrepancy || []).length
        ? [["validation (never fitted)", ps.validation_relative_discrepancy.map((v) => pct(v)).join(" / ")]] : []),
      ["loaded nodes", ps.loaded_discrepancy.map((v) => pct(v)).join(" / ")],
      ["% of h", ps.discrepancy_h.map((v) => pct(v)).join(" / ")],
      ...((ps.compliance_ratio || []).length
        ? [["load compliance ratio", [...ps.compliance_ratio, ...(ps.validation_compliance_ratio || [])]
          .map((x) => ratio(x)).join(" / ")]] : []),
      ["cost", `${num(ps.cost)} m`], ["created", when(ps.created)],
    ];
    const prov = ps.provenance || {};
    show(el("p", null, el("a", { href: "#/parameter-sets" }, "← all parameter sets")),
      el("div", { class: "panel", id: "parameter-set" },
        el("h2", null, ps.name),
        verdictCard(ps.verdict),
        el("dl", { class: "facts" }, facts.map(([k, v]) => [el("dt", null, k), el("dd", null, v)])),
        el("p", null, "From calibration ", el("a", { href: `#/calibrations/${enc(prov.calibration_id)}` }, prov.calibration_id),
          ` (${prov.method}, seed ${prov.seed}, ${prov.chains} chains, ${prov.evaluations} evaluations)`),
        ps.warnings && ps.warnings.length ? el("ul", { class: "warnings" }, ps.warnings.map((w) => el("li", null, w))) : null,
        el("p", null, view3dLink(ps.id), ": the FEM and the FPM shapes per load case, coloured by their discrepancy"),
        exportButtons(ps.id)));
  }

  // A worker makes an export: the first requests answer 202 with Retry-After, then 200 with the
  // file, which is saved under the name the service gives (Content-Disposition).
  const EXPORTS = [["json", "JSON (any engine)"], ["vtu", "VTU (ParaView)"], ["sofa", "SOFA scene"]];

  function exportButtons(id) {
    const status = el("span", { class: "muted", id: "export-status" });
    return el("p", { id: "exports" }, "Export: ",
      EXPORTS.map(([fmt, label]) => el("button", {
        type: "button", "data-format": fmt, onclick: () => download(id, fmt, status),
      }, label)), " ", status);
  }

  async function download(id, fmt, status) {
    const started = Date.now();
    try {
      for (;;) {
        const response = await request("GET", `v1/parameter-sets/${enc(id)}/export?format=${fmt}`, "*/*");
        if (response.status === 202) {
          const wait = Number(response.headers.get("Retry-After") || "1");
          status.textContent = `preparing ${fmt}: a worker makes it (${Math.round((Date.now() - started) / 1000)} s)`;
          await new Promise((resolve) => setTimeout(resolve, 1000 * Math.max(wait, 1)));
          continue;
        }
        const blob = await response.blob();
        const name = (/filename="([^"]+)"/.exec(response.headers.get("Content-Disposition") || "") || [])[1]
          || `${id}.${fmt}`;
        const link = el("a", { href: URL.createObjectURL(blob), download: name });
        document.body.append(link);
        link.click();
        link.remove();
        status.textContent = `${name}: ${blob.size} bytes`;
        status.dataset.done = fmt;
        return;
      }
    } catch (error) {
      status.textContent = errorText(error);
    }
  }

  // ---- 3D view -------------------------------------------------------------------------------
  // The data comes from GET /v1/parameter-sets/{id}/view (202 while a worker makes it, then a
  // binary body); view3d.js (an ES module, with three.js) decodes and draws it.

  let view3d = null; // the open View3D, disposed when the route changes

  function view3dLink(id) {
    return el("a", { href: `#/parameter-sets/${enc(id)}/3d`, class: "view3d-link" }, "3D view");
  }

  // The settle steps of the calibration that made parameter set ``id`` (its result's, one per
  // fitted case), or null when they cannot be read: the 3D view's figures are the result's.
  async function resultSettleSteps(id) {
    try {
      const ps = (await api("GET", `v1/parameter-sets/${enc(id)}`)).body;
      const calibration = ps.provenance && ps.provenance.calibration_id;
      if (!calibration) return null;
      const c = (await api("GET", `v1/calibrations/${enc(calibration)}`)).body;
      return c.result ? c.result.settle_steps : null;
    } catch (error) {
      return null;
    }
  }

  async function view3dPage(id, token) {
    const opened = performance.now();
    const status = el("p", { class: "muted", id: "view3d-status" }, "Loading the 3D view…");
    const panel = el("div", { class: "panel", id: "view3d" },
      el("h2", null, "3D view of parameter set ", id), status);
    show(el("p", null, el("a", { href: `#/parameter-sets/${enc(id)}` }, "← parameter set ", id)), panel);
    for (const file of ["three.module.min.js", "OrbitControls.js"]) { // fetched beside view3d.js
      const href = `web/vendor/three/${file}`;
      if (!document.querySelector(`link[href="${href}"]`)) document.head.append(el("link", { rel: "modulepreload", href }));
    }
    const module = import("./view3d.js"); // loads three.js while the data is fetched
    let buffer;
    try {
      for (;;) {
        const response = await request("GET", `v1/parameter-sets/${enc(id)}/view`, "application/octet-stream");
        if (!alive(token)) return;
        if (response.status !== 202) { buffer = await response.arrayBuffer(); break; }
        const wait = Number(response.headers.get("Retry-After") || "1");
        status.textContent = `A worker is computing the FEM and FPM shapes (${Math.round((performance.now() - opened) / 1000)} s)…`;
        await new Promise((resolve) => setTimeout(resolve, 1000 * Math.max(wait, 1)));
        if (!alive(token)) return;
      }
      const { decodeView, mountView } = await module;
      const settleSteps = await resultSettleSteps(id);
      if (!alive(token)) return;
      status.remove();
      view3d = mountView(panel, decodeView(buffer), {
        request: (path, accept) => request("GET", path, accept), settleSteps,
      });
      await new Promise((resolve) => requestAnimationFrame(() => setTimeout(resolve, 0))); // painted
      if (!alive(token)) return;
      panel.dataset.bytes = String(buffer.byteLength);
      panel.dataset.openMs = String(Math.round(performance.now() - opened)); // since the route
      panel.dataset.shownAt = String(Math.round(performance.now())); // since navigation start
      panel.dataset.ready = "1";
    } catch (error) {
      if (alive(token)) status.replaceChildren(errorPanel(error, "3D view"));
    }
  }

  // ---- Charts (inline SVG) -------------------------------------------------------------------

  function niceStep(span, count) {
    const raw = span / Math.max(1, count);
    const power = 10 ** Math.floor(Math.log10(raw));
    const unit = raw / power;
    return power * (unit < 1.5 ? 1 : unit < 3 ? 2 : unit < 7 ? 5 : 10);
  }

  function linearTicks(lo, hi, count = 5) {
    const step = niceStep(hi - lo, count);
    const ticks = [];
    for (let v = Math.ceil(lo / step) * step; v <= hi + step * 1e-9; v += step) ticks.push(Number(v.toPrecision(12)));
    return ticks;
  }

  function logTicks(lo, hi) {
    const ticks = [];
    const first = Math.floor(Math.log10(lo));
    const last = Math.ceil(Math.log10(hi));
    const multipliers = last - first <= 2 ? [1, 2, 5] : [1];
    for (let e = first; e <= last; e++) {
      for (const m of multipliers) {
        const v = m * 10 ** e;
        if (v >= lo * 0.999 && v <= hi * 1.001) ticks.push(v);
      }
    }
    return ticks;
  }

  // Lines (optionally dashed, with markers) on linear or log y; legend below the plot.
  function lineChart({ series, xLabel, yLabel, logY = false, yFromZero = false, title = null, width = 560, height = 300 }) {
    const ok = (v) => Number.isFinite(v) && (!logY || v > 0);
    const xs = series.flatMap((s) => s.x.filter((v, i) => Number.isFinite(v) && ok(s.y[i])));
    const ys = series.flatMap((s) => s.y.filter(ok));
    if (!xs.length) return el("p", { class: "muted" }, "Nothing to draw.");
    const legendHeight = 16 * series.length + 6;
    const m = { left: 62, right: 14, top: title ? 24 : 10, bottom: 42 };
    const plotW = width - m.left - m.right;
    const plotH = height - m.top - m.bottom;
    let [x0, x1] = [Math.min(...xs), Math.max(...xs)];
    if (x0 === x1) { x0 -= 1; x1 += 1; }
    let [y0, y1] = [Math.min(...ys), Math.max(...ys)];
    if (yFromZero && !logY) y0 = Math.min(0, y0);
    if (logY) { y0 = 10 ** (Math.floor(Math.log10(y0) * 4) / 4); y1 *= 1.15; } else { y1 += (y1 - y0) * 0.08; }
    if (y0 === y1) { y0 = logY ? y0 / 2 : y0 - 1; y1 = logY ? y1 * 2 : y1 + 1; }
    const fy = logY ? Math.log10 : (v) => v;
    const px = (v) => m.left + ((v - x0) / (x1 - x0)) * plotW;
    const py = (v) => m.top + plotH - ((fy(v) - fy(y0)) / (fy(y1) - fy(y0))) * plotH;
    const root = svg("svg", {
      class: "chart", viewBox: `0 0 ${width} ${height + legendHeight}`, role: "img",
      "aria-label": title || yLabel, style: `max-width:${Math.round(width * 1.3)}px`,
    });
    if (title) root.append(svg("text", { x: m.left, y: 15, "font-weight": "600" }, title));
    let yTicks = logY ? logTicks(y0, y1) : linearTicks(y0, y1);
    if (logY && yTicks.length < 3) yTicks = linearTicks(y0, y1, 4).filter((v) => v > 0);
    for (const v of yTicks) {
      root.append(svg("line", { class: "gridline", x1: m.left, x2: m.left + plotW, y1: py(v), y2: py(v) }),
        svg("text", { x: m.left - 6, y: py(v) + 4, "text-anchor": "end" }, num(v, 3)));
    }
    for (const v of linearTicks(x0, x1, 6)) {
      root.append(svg("line", { class: "gridline", x1: px(v), x2: px(v), y1: m.top, y2: m.top + plotH }),
        svg("text", { x: px(v), y: m.top + plotH + 15, "text-anchor": "middle" }, num(v, 4)));
    }
    root.append(
      svg("line", { class: "axis", x1: m.left, x2: m.left, y1: m.top, y2: m.top + plotH }),
      svg("line", { class: "axis", x1: m.left, x2: m.left + plotW, y1: m.top + plotH, y2: m.top + plotH }),
      svg("text", { x: m.left + plotW / 2, y: m.top + plotH + 34, "text-anchor": "middle" }, xLabel),
      svg("text", { x: 14, y: m.top + plotH / 2, "text-anchor": "middle", transform: `rotate(-90 14 ${m.top + plotH / 2})` }, yLabel));
    series.forEach((s, k) => {
      let d = "";
      let pen = "M";
      s.x.forEach((xv, i) => {
        if (Number.isFinite(xv) && ok(s.y[i])) { d += `${pen}${px(xv).toFixed(1)},${py(s.y[i]).toFixed(1)}`; pen = "L"; } else pen = "M";
      });
      const g = svg("g", { "data-series": s.label });
      g.append(svg("path", {
        d, fill: "none", stroke: s.color, "stroke-width": 2, "stroke-dasharray": s.dash ? "6 4" : null,
      }));
      if (s.markers) {
        s.x.forEach((xv, i) => {
          if (Number.isFinite(xv) && ok(s.y[i])) g.append(svg("circle", { cx: px(xv), cy: py(s.y[i]), r: 3, fill: s.color }));
        });
      }
      root.append(g);
      const ly = height + 12 + 16 * k;
      root.append(
        svg("line", { x1: m.left, x2: m.left + 26, y1: ly - 4, y2: ly - 4, stroke: s.color, "stroke-width": 2, "stroke-dasharray": s.dash ? "6 4" : null }),
        svg("text", { x: m.left + 32, y: ly }, s.label));
    });
    return root;
  }

  // The calibration's jobs on its workers: one lane per worker, a bar per job from its start
  // to its end (seconds since the first job started), the critical path's bars outlined.
  const JOB_COLORS = { fem: "#7f7f7f", chain: COLORS[0], damping: COLORS[1], case: COLORS[2], finalize: COLORS[4] };
  function jobKind(name) {
    if (name.startsWith("damping: ")) return "case";
    if (name.startsWith("chain")) return "chain";
    if (name.startsWith("damping")) return "damping";
    return name === "finalize" ? "finalize" : "fem";
  }

  function timelinePanel(r) {
    const jobs = r.jobs || [];
    if (!jobs.length) return null;
    const t0 = Math.min(...jobs.map((j) => j.start));
    const wall = Math.max(...jobs.map((j) => j.end)) - t0;
    const cpu = jobs.reduce((sum, j) => sum + j.cpu, 0);
    return el("div", { class: "panel", id: "timeline" },
      el("h3", null, "Jobs on the workers"),
      el("p", null, `${jobs.length} jobs on ${new Set(jobs.map((j) => j.worker)).size} worker(s): `,
        `wall ${seconds(wall)}, critical path ${seconds(r.critical_path_seconds)} `,
        `(${(r.critical_path || []).join(" → ")}), CPU ${seconds(cpu)}`),
      timelineChart(jobs, t0, wall, new Set(r.critical_path || [])));
  }

  // Rows of the timeline: per worker, as many as its jobs overlap (a job on the first row of
  // its worker that is free by its start). Returns [[worker, row]...] and each job's row index.
  function timelineRows(jobs) {
    const rows = [];
    const freeAt = [];
    const rowOf = jobs.map((j) => {
      let i = rows.findIndex((r, k) => r[0] === j.worker && freeAt[k] <= j.start);
      if (i < 0) {
        const last = rows.map((r) => r[0]).lastIndexOf(j.worker);
        i = last < 0 ? rows.length : last + 1;
        rows.splice(i, 0, [j.worker, rows.filter((r) => r[0] === j.worker).length]);
        freeAt.splice(i, 0, -Infinity);
      }
      freeAt[i] = j.end;
      return rows[i];
    });
    return { rows, rowOf };
  }

  function timelineChart(jobs, t0, wall, critical) {
    const { rows, rowOf } = timelineRows(jobs);
    const width = 1100;
    const laneH = 28;
    const m = { left: 110, right: 20, top: 26, bottom: 40 };
    const plotW = width - m.left - m.right;
    const height = m.top + laneH * rows.length + m.bottom;
    const px = (t) => m.left + ((t - t0) / Math.max(wall, 1e-9)) * plotW;
    const root = svg("svg", {
      class: "chart", viewBox: `0 0 ${width} ${height}`, role: "img",
      "aria-label": "the calibration's jobs on its workers over time",
    });
    const bottom = m.top + laneH * rows.length;
    linearTicks(0, wall, 8).forEach((v) => root.append(
      svg("line", { class: "gridline", x1: px(t0 + v), x2: px(t0 + v), y1: m.top, y2: bottom }),
      svg("text", { x: px(t0 + v), y: bottom + 15, "text-anchor": "middle" }, num(v, 3))));
    root.append(svg("text", { x: m.left + plotW / 2, y: bottom + 33, "text-anchor": "middle" },
      "seconds since the first job started"));
    rows.forEach(([w, k], i) => {
      if (k === 0) root.append(svg("text", { x: m.left - 8, y: m.top + laneH * i + 18, "text-anchor": "end" }, w.slice(0, 12)));
    });
    jobs.forEach((j, n) => {
      const lane = rows.indexOf(rowOf[n]);
      const kind = jobKind(j.name);
      const x = px(j.start);
      const bar = svg("rect", {
        x, y: m.top + laneH * lane + 4, width: Math.max(px(j.end) - x, 1.5), height: laneH - 8,
        fill: JOB_COLORS[kind], "data-job": j.name,
        stroke: critical.has(j.name) ? "#111" : null, "stroke-width": critical.has(j.name) ? 2 : null,
      }, svg("title", null, `${j.name} on ${j.worker}: ${seconds(j.end - j.start)}, CPU ${seconds(j.cpu)}`));
      root.append(bar);
    });
    let lx = m.left;
    Object.entries({ fem: "FEM", chain: "chains", damping: "damping", case: "damping tasks (runs, validation)", finalize: "finalize" }).forEach(([kind, label]) => {
      root.append(svg("rect", { x: lx, y: 6, width: 12, height: 12, fill: JOB_COLORS[kind] }),
        svg("text", { x: lx + 16, y: 16 }, label));
      lx += 30 + 8 * label.length;
    });
    root.append(svg("rect", { x: lx, y: 6, width: 12, height: 12, fill: "none", stroke: "#111", "stroke-width": 2 }),
      svg("text", { x: lx + 16, y: 16 }, "critical path"));
    return root;
  }

  // Horizontal bars with their values.
  // A bar's label that fits the chart's left margin (the whole name in its tooltip).
  const LABEL_CHARS = 20;
  const shortLabel = (text) => (text.length > LABEL_CHARS ? `${text.slice(0, LABEL_CHARS - 1)}…` : text);

  function barChart(items, label) {
    const width = 560;
    const rowH = 24;
    const m = { left: 140, right: 70, top: 22 };
    const height = m.top + rowH * items.length + 6;
    const top = Math.max(...items.map((i) => i.value).filter(Number.isFinite), 1e-9) * 1.05;
    const plotW = width - m.left - m.right;
    const root = svg("svg", {
      class: "chart", viewBox: `0 0 ${width} ${height}`, role: "img", "aria-label": label,
      style: `max-width:${Math.round(width * 1.3)}px`,
    },
      svg("text", { x: m.left, y: 14 }, label));
    items.forEach((item, j) => {
      const y = m.top + rowH * j;
      const w = Number.isFinite(item.value) ? (item.value / top) * plotW : 0;
      root.append(
        svg("text", { x: m.left - 8, y: y + 15, "text-anchor": "end" }, shortLabel(item.label),
          svg("title", null, item.label)),
        svg("rect", { x: m.left, y: y + 3, width: Math.max(0, w), height: rowH - 8, fill: item.color }),
        svg("text", { x: m.left + w + 6, y: y + 15 }, pct(item.value)));
    });
    return root;
  }

  // ---- Start ---------------------------------------------------------------------------------

  document.addEventListener("DOMContentLoaded", () => {
    document.getElementById("key-form").addEventListener("submit", keyGiven);
    document.getElementById("key-dismiss").addEventListener("click", keyDismissed);
    showKeyStatus();
    window.addEventListener("hashchange", route);
    route();
  });
})();
