// The GSA results page's 3D viewer: three synchronised views (source, target, aligned
// overlay) of the job's .splat previews, drawn by Spark (3DGS on three.js).
// The page (built by gsa/viewer/page.py) carries a JSON config in #gsa-config; this
// script only reads it and the preview files it names (same origin, no CDN).
// window.gsaViewer reports state for people and tests: {ready, firstFrameMs, error, ...}.
// The guide (config.guide, one-source results) is in guide.js: alternatives, point pairs, up and front axes.
import { SparkRenderer, SplatMesh } from "@sparkjsdev/spark";
import * as THREE from "three";
import { pollJob, setupGuide } from "./guide.js";

const BACKGROUND = 0x1b1d22;
const TARGET_TINT = [0.15, 0.45, 1.0];
const SOURCE_TINTS = [
  [1.0, 0.5, 0.1],
  [0.95, 0.2, 0.75],
  [0.3, 0.9, 0.3],
  [1.0, 0.9, 0.2],
];
// A many job's models (gsa/viewer/page.py MANY_TINTS): the reference first colour, then the sources'.
const MANY_TINTS = [TARGET_TINT, ...SOURCE_TINTS];
const UPS = { "+z": [0, 0, 1], "+y": [0, 1, 0], "-y": [0, -1, 0] };

const state = (window.gsaViewer = { ready: false, firstFrameMs: null, error: null, frames: 0, panes: {} });

function fail(err) {
  state.error = String(err && err.message ? err.message : err);
  const box = document.getElementById("viewer-status");
  if (box) box.textContent = `viewer: ${state.error}`;
  document.documentElement.dataset.viewer = "error";
  console.warn("gsa viewer:", state.error);
}

async function fetchBytes(url) {
  const r = await fetch(url, { credentials: "same-origin" });
  if (!r.ok) throw new Error(`${r.status} loading a preview`);
  return new Uint8Array(await r.arrayBuffer());
}

// Centre and radius of a .splat file's positions (32-byte records, float32 x y z first).
function bounds(bytes) {
  const n = Math.floor(bytes.byteLength / 32);
  const f = new Float32Array(bytes.buffer, bytes.byteOffset, n * 8);
  const c = [0, 0, 0];
  for (let i = 0; i < n; i++) for (let k = 0; k < 3; k++) c[k] += f[i * 8 + k] / n;
  let ss = 0;
  for (let i = 0; i < n; i++) for (let k = 0; k < 3; k++) ss += (f[i * 8 + k] - c[k]) ** 2 / n;
  return { center: new THREE.Vector3(...c), radius: Math.max(Math.sqrt(ss), 1e-6) };
}

// A copy whose colours are the tint shaded by each splat's own lightness.
function tinted(bytes, tint) {
  const out = bytes.slice();
  for (let o = 24; o < out.length; o += 32) {
    const l = (0.299 * out[o] + 0.587 * out[o + 1] + 0.114 * out[o + 2]) / 255;
    const shade = 0.45 + 0.55 * l;
    for (let k = 0; k < 3; k++) out[o + k] = Math.round(255 * tint[k] * shade);
  }
  return out;
}

function makeMesh(bytes) {
  return new SplatMesh({ fileBytes: bytes.slice(), fileType: "splat" });
}

class Pane {
  constructor(name, canvas, frame) {
    this.name = name;
    this.canvas = canvas;
    this.frame = frame;
    this.renderer = new THREE.WebGLRenderer({ canvas, antialias: false, preserveDrawingBuffer: true });
    this.renderer.setClearColor(BACKGROUND, 1);
    this.scene = new THREE.Scene();
    this.spark = new SparkRenderer({ renderer: this.renderer, onDirty: () => (this.dirty = true) });
    this.scene.add(this.spark);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 1000);
    this.meshes = {};
    this.dirty = true;
    this.painted = false;
    this.up = null; // a THREE.Vector3 from the guide's up-axis choice, else the page's up
    this.view = null; // its own orbit while the views are unlinked (picking points), else the shared one
  }

  add(key, mesh) {
    this.meshes[key] = mesh;
    this.scene.add(mesh);
  }

  show(key, visible) {
    if (this.meshes[key]) this.meshes[key].visible = visible;
    this.dirty = true;
  }

  resize() {
    const w = this.canvas.clientWidth;
    const h = this.canvas.clientHeight;
    if (w && h && (this.canvas.width !== w || this.canvas.height !== h)) {
      this.renderer.setSize(w, h, false);
      this.camera.aspect = w / h;
      this.camera.updateProjectionMatrix();
      this.dirty = true;
    }
  }

  place(view) {
    const { center, radius } = this.frame;
    // The guide's up-axis choice turns this pane to show that axis up.
    const up = this.up ? this.up.clone() : new THREE.Vector3(...UPS[view.up]);
    const e1 = Math.abs(up.x) > 0.9 ? new THREE.Vector3(0, 1, 0) : new THREE.Vector3(1, 0, 0);
    e1.sub(up.clone().multiplyScalar(e1.dot(up))).normalize();
    const e2 = up.clone().cross(e1);
    const d = radius * view.distance;
    const dir = e1
      .multiplyScalar(Math.cos(view.elevation) * Math.cos(view.azimuth))
      .add(e2.multiplyScalar(Math.cos(view.elevation) * Math.sin(view.azimuth)))
      .add(up.clone().multiplyScalar(Math.sin(view.elevation)));
    this.camera.position.copy(center).addScaledVector(dir, d);
    this.camera.up.copy(up);
    this.camera.near = Math.max(d - 4 * radius, d * 0.01);
    this.camera.far = d + 6 * radius;
    this.camera.lookAt(center);
    this.camera.updateProjectionMatrix();
  }

  // Rendered at least once with something drawn (Spark sorts in a worker: the first
  // frames after loading may still be empty).
  hasPixels() {
    const gl = this.renderer.getContext();
    const w = gl.drawingBufferWidth;
    const h = gl.drawingBufferHeight;
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    const bg = new THREE.Color(BACKGROUND);
    const br = Math.round(bg.r * 255);
    const bb = Math.round(bg.b * 255);
    for (let i = 0; i < px.length; i += 4 * 7) {
      if (Math.abs(px[i] - br) > 8 || Math.abs(px[i + 2] - bb) > 8) return true;
    }
    return false;
  }
}

// Drag orbits all views (or only its own while they are unlinked: pane.view), the wheel zooms; a press that does not move is a click (the guide picks
// points with it). Focused views orbit with the arrow keys and zoom with +/-; Enter or Space is a
// click at the view's centre, so picking works from the keyboard.
function controls(panes, view, onChange, onClick) {
  for (const pane of panes) {
    const canvas = pane.canvas;
    let last = null;
    let down = null;
    canvas.addEventListener("pointerdown", (e) => {
      last = [e.clientX, e.clientY];
      down = last;
      canvas.setPointerCapture(e.pointerId);
    });
    canvas.addEventListener("pointerup", (e) => {
      if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 4) onClick(pane, e.clientX, e.clientY);
      last = down = null;
    });
    canvas.addEventListener("keydown", (e) => {
      const v = pane.view || view;
      const step = { ArrowLeft: [0.1, 0], ArrowRight: [-0.1, 0], ArrowUp: [0, 0.1], ArrowDown: [0, -0.1] }[e.key];
      const zoom = { "+": 0.9, "=": 0.9, "-": 1.1, _: 1.1 }[e.key];
      if (step) {
        v.azimuth += step[0];
        v.elevation = Math.max(-1.5, Math.min(1.5, v.elevation + step[1]));
      } else if (zoom) {
        v.distance = Math.max(0.5, Math.min(20, v.distance * zoom));
      } else if (e.key === "Enter" || e.key === " ") {
        const r = canvas.getBoundingClientRect();
        onClick(pane, r.left + r.width / 2, r.top + r.height / 2);
      } else {
        return;
      }
      e.preventDefault();
      onChange();
    });
    canvas.addEventListener("pointermove", (e) => {
      if (!last) return;
      const v = pane.view || view;
      v.azimuth -= (e.clientX - last[0]) * 0.01;
      v.elevation = Math.max(-1.5, Math.min(1.5, v.elevation + (e.clientY - last[1]) * 0.01));
      last = [e.clientX, e.clientY];
      onChange();
    });
    canvas.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        const v = pane.view || view;
        v.distance = Math.max(0.5, Math.min(20, v.distance * Math.exp(e.deltaY * 0.001)));
        onChange();
      },
      { passive: false },
    );
  }
}

// The render loop: places and draws each dirty pane, marks the page ready once all have pixels.
function startLoop(panes, view) {
  const loop = () => {
    for (const p of Object.values(panes)) {
      p.resize();
      if (!p.dirty && p.painted) continue;
      p.dirty = false;
      p.place(p.view || view);
      p.renderer.render(p.scene, p.camera);
      if (!p.painted && p.hasPixels()) p.painted = true;
    }
    state.frames += 1;
    if (!state.ready && Object.values(panes).every((p) => p.painted)) {
      state.firstFrameMs = performance.now();
      state.ready = true;
      document.documentElement.dataset.viewer = "ready";
      document.getElementById("viewer-status").textContent = `ready: first frame ${(state.firstFrameMs / 1000).toFixed(2)} s after navigation`;
    }
    requestAnimationFrame(loop);
  };
  requestAnimationFrame(loop);
}

// A row-major 4x4 (many.json) as a THREE.Matrix4.
function matrix4(rows) {
  return new THREE.Matrix4().set(...rows.flat());
}

// A many job (issue 30): every model's preview (its own frame) placed by its transform into the
// reference frame in one view, a checkbox per model (data-many-model="k"), the tint toggle.
// state.visible: {model0: true, ...}; state.many: {models, shown}.
async function mainMany(config) {
  const el = (id) => document.getElementById(id);
  const models = config.many.models;
  const usable = models.map((m) => Boolean(m.preview && m.transform));
  state.many = { models: models.length, shown: models.length };
  if (!usable.some(Boolean)) {
    el("viewer-status").textContent = "no 3D previews in this result";
    document.documentElement.dataset.viewer = "no-preview";
    state.ready = true;
    return;
  }
  const bytes = await Promise.all(models.map((m, k) => (usable[k] ? fetchBytes(m.preview) : null)));
  // The view's frame: the reference's bounds moved into the reference frame (its transform is
  // the identity), else the first model's.
  const first = models.findIndex((m, k) => usable[k] && m.reference);
  const k0 = first >= 0 ? first : usable.indexOf(true);
  const b0 = bounds(bytes[k0]);
  const m0 = matrix4(models[k0].transform);
  const frame = { center: b0.center.clone().applyMatrix4(m0), radius: 1.4 * b0.radius * m0.getMaxScaleOnAxis() };
  const pane = new Pane("many", el("view-many"), frame);
  const panes = { many: pane };
  state.panes = panes;
  const meshes = { tinted: {}, natural: {} };
  const placed = (b, k) => {
    const mesh = makeMesh(b);
    matrix4(models[k].transform).decompose(mesh.position, mesh.quaternion, mesh.scale);
    return mesh;
  };
  bytes.forEach((b, k) => {
    if (b) pane.add(`model${k}`, (meshes.tinted[k] = placed(tinted(b, MANY_TINTS[k % MANY_TINTS.length]), k)));
  });
  const view = { azimuth: 0.8, elevation: 0.45, distance: 4.2, up: config.up || "+z" };
  controls([pane], view, () => (pane.dirty = true), () => {});
  const tint = el("toggle-tint");
  const apply = () => {
    const useTint = !tint || tint.checked;
    const on = {};
    for (const box of document.querySelectorAll("input[data-many-model]")) on[`model${box.dataset.manyModel}`] = box.checked;
    bytes.forEach((b, k) => {
      if (!b) return;
      if (!useTint && !meshes.natural[k]) pane.add(`natural${k}`, (meshes.natural[k] = placed(b, k)));
      meshes.tinted[k].visible = useTint && on[`model${k}`] !== false;
      if (meshes.natural[k]) meshes.natural[k].visible = !useTint && on[`model${k}`] !== false;
    });
    pane.dirty = true;
    state.visible = { ...on, tint: useTint };
    state.many.shown = Object.values(on).filter(Boolean).length;
  };
  for (const box of document.querySelectorAll("input[data-many-model]")) box.addEventListener("change", apply);
  if (tint) tint.addEventListener("change", apply);
  const upPick = el("pick-up");
  if (upPick) {
    upPick.value = view.up;
    upPick.addEventListener("change", () => {
      view.up = upPick.value;
      pane.dirty = true;
    });
  }
  apply();
  await Promise.all(Object.values(meshes.tinted).map((m) => m.initialized));
  state.loadedMs = performance.now();
  startLoop(panes, view);
}

async function main() {
  const config = JSON.parse(document.getElementById("gsa-config").textContent);
  if (config.poll) pollJob(config.poll); // a job still running: reload when it has finished
  if (config.many) return mainMany(config);
  const models = config.results;
  const el = (id) => document.getElementById(id);
  if (!models.length || !models[0].preview.target) {
    const status = el("viewer-status");
    if (status) status.textContent = models.length ? "no 3D previews in this result (made without the preview output)" : "nothing to show in 3D yet";
    document.documentElement.dataset.viewer = "no-preview";
    state.ready = true;
    return;
  }
  const targetBytes = await fetchBytes(models[0].preview.target);
  const sourceBytes = await Promise.all(models.map((m) => fetchBytes(m.preview.source)));
  const alignedBytes = await Promise.all(models.map((m) => fetchBytes(m.preview.aligned)));
  const targetFrame = bounds(targetBytes);
  const panes = {
    source: new Pane("source", el("view-source"), bounds(sourceBytes[0])),
    target: new Pane("target", el("view-target"), targetFrame),
    overlay: new Pane("overlay", el("view-overlay"), targetFrame),
  };
  state.panes = panes;
  sourceBytes.forEach((b, i) => panes.source.add(`source${i}`, makeMesh(b)));
  panes.target.add("target", makeMesh(targetBytes));
  const tintedMeshes = { target: makeMesh(tinted(targetBytes, TARGET_TINT)) };
  alignedBytes.forEach((b, i) => {
    tintedMeshes[`source${i}`] = makeMesh(tinted(b, SOURCE_TINTS[i % SOURCE_TINTS.length]));
  });
  for (const [k, m] of Object.entries(tintedMeshes)) panes.overlay.add(k, m);
  const natural = {};

  const view = { azimuth: 0.8, elevation: 0.45, distance: 4.2, up: config.up || "+z" };
  const redraw = () => {
    for (const p of Object.values(panes)) p.dirty = true;
  };
  const clicks = { handler: () => {} }; // the guide's, when the page has one
  controls(Object.values(panes), view, redraw, (pane, x, y) => clicks.handler(pane, x, y));

  // The source pane shows one source at a time (a multi-model job has several).
  const pick = el("pick-source");
  const showSource = (i) => {
    sourceBytes.forEach((_, j) => panes.source.show(`source${j}`, j === i));
    panes.source.frame = bounds(sourceBytes[i]);
    redraw();
  };
  showSource(0);
  if (pick) pick.addEventListener("change", () => showSource(Number(pick.value)));
  const upPick = el("pick-up");
  if (upPick) {
    upPick.value = view.up;
    upPick.addEventListener("change", () => {
      view.up = upPick.value;
      for (const p of Object.values(panes)) p.up = null; // back from the guide's per-model axes
      redraw();
    });
  }
  // Unlinked, each view orbits on its own: two models in different frames show the same side
  // only when each is turned separately (point picking needs that).
  const link = el("link-views");
  if (link) {
    link.addEventListener("change", () => {
      for (const p of Object.values(panes)) p.view = link.checked ? null : { ...(p.view || view) };
      state.linked = link.checked;
      redraw();
    });
  }
  // Overlay toggles: one checkbox per model (data-model="target" / "source0" ...), and the tint.
  const tint = el("toggle-tint");
  const visibleKeys = () => {
    const on = {};
    for (const box of document.querySelectorAll("input[data-model]")) on[box.dataset.model] = box.checked;
    return on;
  };
  // The guide may show another pose of source 0 (an alternative): alt.pose set, the aligned
  // preview hidden and the source preview drawn at that pose instead.
  const alt = { pose: null, tinted: null, natural: null };
  const applyToggles = () => {
    const on = visibleKeys();
    const useTint = !tint || tint.checked;
    if (!useTint) {
      natural.target ??= makeMesh(targetBytes);
      alignedBytes.forEach((b, i) => (natural[`source${i}`] ??= makeMesh(b)));
      for (const [k, m] of Object.entries(natural)) if (!m.parent) panes.overlay.scene.add(m);
    }
    if (alt.pose) {
      const key = useTint ? "tinted" : "natural";
      if (!alt[key]) {
        alt[key] = makeMesh(useTint ? tinted(sourceBytes[0], SOURCE_TINTS[0]) : sourceBytes[0]);
        panes.overlay.add(useTint ? "alternative" : "alternativeNatural", alt[key]);
      }
      alt.pose.decompose(alt[key].position, alt[key].quaternion, alt[key].scale);
    }
    for (const k of Object.keys(tintedMeshes)) {
      const shown = on[k] !== false && !(alt.pose && k === "source0");
      tintedMeshes[k].visible = useTint && shown;
      if (natural[k]) natural[k].visible = !useTint && shown;
    }
    if (alt.tinted) alt.tinted.visible = Boolean(alt.pose) && useTint && on.source0 !== false;
    if (alt.natural) alt.natural.visible = Boolean(alt.pose) && !useTint && on.source0 !== false;
    panes.overlay.dirty = true;
    state.visible = { ...on, tint: useTint };
  };
  for (const box of document.querySelectorAll("input[data-model]")) box.addEventListener("change", applyToggles);
  if (tint) tint.addEventListener("change", applyToggles);
  applyToggles();

  if (config.guide) {
    const showPose = (matrix) => {
      alt.pose = matrix;
      applyToggles();
    };
    const place = (pane) => pane.place(pane.view || view); // a click may come before the next frame placed it
    clicks.handler = setupGuide(config.guide, { panes, sourceBytes: sourceBytes[0], targetBytes, redraw, showPose, place, state });
  }

  await Promise.all(
    Object.values(panes).flatMap((p) => Object.values(p.meshes).map((m) => m.initialized)),
  );
  state.loadedMs = performance.now();
  startLoop(panes, view);
}

main().catch(fail);
