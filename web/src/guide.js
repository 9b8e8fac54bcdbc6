// The results page's guide (gsa/viewer/page.py _guide; config.guide, one-source results only):
// step through the result's alternatives on the overlay, pick point pairs on the source and
// target views, choose each model's up axis (and, optionally, the way each faces). Each control
// asks for a follow-up alignment: on the service's page a POST to the page's refine route, then
// the follow-up job's page opens; on `gsa view`'s page (no job to refine) the equivalent
// `gsa align` command, to copy. A known scale
// (its input; empty: not fixed) goes with whichever control is used: fixed_scale in the request,
// --scale S in the command; an invalid one stops the control, with a message beside the input.
//
// Frames: the previews, and so every point picked here, are in align()'s internal frame; the
// requests and commands take each file's own coordinates (config.guide.to_file rotates one into
// the other, identity for PLY, a 180° turn about x for SPZ and GLB).
import * as THREE from "three";

const AXES = { "+x": [1, 0, 0], "-x": [-1, 0, 0], "+y": [0, 1, 0], "-y": [0, -1, 0], "+z": [0, 0, 1], "-z": [0, 0, -1] };
const PAIR_COLOURS = [0xffd400, 0x00e5ff, 0xff4df0, 0x7dff5a, 0xff8c1a, 0xffffff];
const MIN_PAIRS = 3; // the closed-form Sim(3) needs three (gsa.align.guided)
const PICK_RADIUS_PX = 8;
const SPHERE = new THREE.SphereGeometry(1, 12, 8);

const rotate = (R, p) => R.map((row) => row[0] * p[0] + row[1] * p[1] + row[2] * p[2]);
const rotateBack = (R, p) => [0, 1, 2].map((k) => R[0][k] * p[0] + R[1][k] * p[1] + R[2][k] * p[2]);
const round = (v) => Number(v.toPrecision(7)); // float32 previews: more digits would be noise
const show = (v, d = 3) => (v === null || v === undefined ? "—" : Number(v).toFixed(d));

// Screen position (client px) and depth of internal point (x, y, z) in the pane's current camera.
function projector(pane) {
  pane.camera.updateMatrixWorld();
  const m = new THREE.Matrix4().multiplyMatrices(pane.camera.projectionMatrix, pane.camera.matrixWorldInverse).elements;
  const r = pane.canvas.getBoundingClientRect();
  return (x, y, z) => {
    const w = m[3] * x + m[7] * y + m[11] * z + m[15];
    if (w <= 0) return null;
    const sx = r.left + (0.5 + (0.5 * (m[0] * x + m[4] * y + m[8] * z + m[12])) / w) * r.width;
    const sy = r.top + (0.5 - (0.5 * (m[1] * x + m[5] * y + m[9] * z + m[13])) / w) * r.height;
    return [sx, sy, w];
  };
}

// The nearest-to-the-camera splat centre within a few pixels of (x, y): what the person sees
// there. Faint splats (alpha < 40/255) are skipped: they are not what a click means.
function nearestSplat(pane, bytes, x, y) {
  const project = projector(pane);
  const n = Math.floor(bytes.byteLength / 32);
  const f = new Float32Array(bytes.buffer, bytes.byteOffset, n * 8);
  let best = -1;
  let bestDepth = Infinity;
  for (let i = 0; i < n; i++) {
    if (bytes[i * 32 + 27] < 40) continue;
    const s = project(f[i * 8], f[i * 8 + 1], f[i * 8 + 2]);
    if (!s || (s[0] - x) ** 2 + (s[1] - y) ** 2 > PICK_RADIUS_PX ** 2 || s[2] >= bestDepth) continue;
    best = i;
    bestDepth = s[2];
  }
  return best < 0 ? null : [f[best * 8], f[best * 8 + 1], f[best * 8 + 2]];
}

// A dot drawn over the splats (no depth test) where a point was picked.
function addMarker(pane, p, colour) {
  const m = new THREE.Mesh(SPHERE, new THREE.MeshBasicMaterial({ color: colour, depthTest: false, depthWrite: false, transparent: true }));
  m.renderOrder = 999;
  m.scale.setScalar(pane.frame.radius * 0.03);
  m.position.set(...p);
  pane.scene.add(m);
  pane.dirty = true;
  return m;
}

function removeMarker(pane, m) {
  pane.scene.remove(m);
  m.material.dispose();
  pane.dirty = true;
}

function button(text, label) {
  const b = document.createElement("button");
  b.type = "button";
  b.textContent = text;
  if (label) b.setAttribute("aria-label", label);
  return b;
}

// Polls a running job's state (the service page of a job not yet finished) and reloads the page
// when it has finished, so the follow-up job's result shows without a click.
export async function pollJob(url) {
  const box = document.createElement("p");
  box.id = "job-state";
  box.className = "status";
  box.setAttribute("aria-live", "polite");
  (document.querySelector("header") || document.body).after(box);
  for (;;) {
    try {
      const r = await fetch(url, { credentials: "same-origin", cache: "no-store" });
      if (r.status === 401 || r.status === 403) {
        box.textContent = "this page's link has expired: open a new one to follow the job";
        return;
      }
      if (r.ok) {
        const s = await r.json();
        const stage = s.stage ? ` (${s.stage}, ${Math.round(100 * s.progress)} %)` : "";
        box.textContent = `job ${s.id}: ${s.state}${stage}`;
        if (s.terminal) {
          box.textContent += "; loading its result…";
          window.location.reload();
          return;
        }
      }
    } catch {
      // a dropped connection: try again on the next round
    }
    await new Promise((done) => setTimeout(done, 1000));
  }
}

// Wires the guide's controls; returns the views' click handler (point picking).
export function setupGuide(guide, { panes, sourceBytes, targetBytes, redraw, showPose, place, state }) {
  const el = (id) => document.getElementById(id);
  const out = el("guide-out");
  const g = (state.guide = { mode: guide.mode, position: -1, pairs: [], pending: {}, picking: false, requests: [], child: null });
  const bytesOf = { source: sourceBytes, target: targetBytes };
  const markers = []; // [{source, target}] beside g.pairs, and g.pendingMarkers for the half pair
  let pendingMarkers = {};
  const submitButtons = ["alt-use", "pairs-submit", "up-submit"].map(el);
  // For tests and people at the console: where an internal point shows in a pane (client px).
  state.project = (name, p) => {
    place(panes[name]);
    const s = projector(panes[name])(...p);
    return s && [s[0], s[1]];
  };

  const cli = (args) =>
    `gsa align ${guide.source} ${guide.target} ${args} --out refined/result.json --preview && gsa view refined/result.json`;

  // The known scale: null when empty, a positive finite number, or undefined (and the message
  // shown) when it is anything else.
  const scaleInput = el("scale-input");
  const scaleError = el("scale-error");
  const showScaleError = (message) => {
    scaleError.textContent = message;
    scaleError.hidden = !message;
    scaleInput.setAttribute("aria-invalid", String(Boolean(message)));
  };
  function knownScale() {
    const raw = scaleInput.value.trim();
    if (raw === "") {
      showScaleError("");
      return null;
    }
    const v = Number(raw);
    if (!Number.isFinite(v) || v <= 0) {
      showScaleError(`"${raw}" is not a scale: give a positive number (e.g. 2.5), or leave it empty`);
      scaleInput.focus();
      return undefined;
    }
    showScaleError("");
    return v;
  }
  scaleInput.addEventListener("input", () => showScaleError(""));

  function showCommand(command) {
    const intro = document.createElement("p");
    intro.textContent = "Run this where the input files are (then the refined result opens in a new page):";
    const pre = document.createElement("pre");
    pre.id = "guide-command";
    pre.tabIndex = 0;
    pre.textContent = command;
    const copy = button("Copy the command");
    copy.id = "guide-copy";
    copy.addEventListener("click", () =>
      navigator.clipboard.writeText(command).then(
        () => (copy.textContent = "Copied"),
        () => window.getSelection().selectAllChildren(pre), // no clipboard: select it for Ctrl-C
      ),
    );
    out.replaceChildren(intro, pre, copy);
  }

  // hints: the request's body; args: the command's (after `prefix`, lines to run before it).
  async function submit(hints, args, prefix = "") {
    const scale = knownScale();
    if (scale === undefined) return; // nothing sent
    if (scale !== null) {
      hints = { ...hints, fixed_scale: scale };
      args += ` --scale ${scale}`;
    }
    const command = prefix + cli(args);
    g.requests.push(hints);
    if (guide.mode !== "service") {
      showCommand(command);
      return;
    }
    const was = submitButtons.map((b) => b.disabled);
    submitButtons.forEach((b) => (b.disabled = true)); // one follow-up per click
    out.textContent = "starting the follow-up job…";
    try {
      const r = await fetch(guide.refine, {
        method: "POST",
        credentials: "same-origin",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify(hints),
      });
      const body = await r.json().catch(() => ({}));
      if (!r.ok) throw new Error(`the service refused it (${r.status}): ${body.detail || body.title || "no reason given"}`);
      g.child = body.job.id;
      out.textContent = `follow-up job ${body.job.id} started; opening its page…`;
      window.location.assign(body.view_url);
    } catch (err) {
      out.textContent = err.message;
      submitButtons.forEach((b, i) => (b.disabled = was[i]));
    }
  }

  // Alternatives: position -1 is the chosen pose (the aligned preview), k >= 0 alternatives[k]
  // drawn as the source preview at that pose.
  const alts = guide.alternatives;
  const label = el("alt-label");
  const use = el("alt-use");
  const step = (k) => {
    g.position = k;
    if (k < 0) {
      showPose(null);
      label.textContent = `the chosen pose (${alts.length} alternative${alts.length === 1 ? "" : "s"})`;
    } else {
      const a = alts[k];
      showPose(new THREE.Matrix4().set(...a.transform.flat()));
      label.textContent =
        `alternative ${a.index} (${k + 1} of ${alts.length}): ${show(a.rotation_offset_deg, 0)}° from the chosen, ` +
        `scale ×${show(a.scale_ratio, 2)}, score ${show(a.score)}`;
    }
    use.disabled = k < 0;
  };
  const cycle = (d) => step(((g.position + 1 + d + alts.length + 1) % (alts.length + 1)) - 1);
  el("alt-prev").addEventListener("click", () => cycle(-1));
  el("alt-next").addEventListener("click", () => cycle(1));
  el("alt-prev").disabled = el("alt-next").disabled = alts.length === 0;
  use.addEventListener("click", () => {
    const a = alts[g.position];
    if (a) submit({ alternative: a.index }, `--init ${guide.result} --alternative ${a.index}`);
  });
  step(-1);

  // Point pairs.
  const toggle = el("pick-toggle");
  const list = el("pair-list");
  const pickState = el("pick-state");
  const undo = el("pairs-undo");
  const sendPairs = el("pairs-submit");
  const fileCoords = (role, p) => rotate(guide.to_file[role], p).map(round);
  const text = (p) => `(${p.map((v) => v.toPrecision(4)).join(", ")})`;
  const dropPair = (i) => {
    for (const role of ["source", "target"]) removeMarker(panes[role], markers[i][role]);
    g.pairs.splice(i, 1);
    markers.splice(i, 1);
    renderPairs();
  };
  function renderPairs() {
    list.replaceChildren(
      ...g.pairs.map((pair, i) => {
        const li = document.createElement("li");
        li.textContent = `source ${text(fileCoords("source", pair.source))} ↔ target ${text(fileCoords("target", pair.target))} `;
        const rm = button("remove", `remove pair ${i + 1}`);
        rm.addEventListener("click", () => dropPair(i));
        li.append(rm);
        return li;
      }),
    );
    const half = g.pending.source ? "target" : g.pending.target ? "source" : null;
    const n = g.pairs.length;
    pickState.textContent =
      `${n} pair${n === 1 ? "" : "s"}` +
      (half ? `; now the matching point on the ${half} view` : g.picking ? "; click a point on the source view" : "") +
      (n < MIN_PAIRS ? ` (${MIN_PAIRS} or more to align)` : "");
    sendPairs.disabled = n < MIN_PAIRS;
    undo.disabled = n === 0 && !half;
  }
  toggle.addEventListener("click", () => {
    g.picking = !g.picking;
    toggle.setAttribute("aria-pressed", String(g.picking));
    toggle.textContent = g.picking ? "Stop picking" : "Pick point pairs";
    document.documentElement.toggleAttribute("data-picking", g.picking);
    // Picking: each view orbits on its own (the source and the target are seldom seen from the
    // same side at one shared orbit); done: together again.
    const link = el("link-views");
    if (link && link.checked === g.picking) {
      link.checked = !g.picking;
      link.dispatchEvent(new Event("change"));
    }
    renderPairs();
  });
  undo.addEventListener("click", () => {
    if (g.pending.source || g.pending.target) {
      for (const [role, m] of Object.entries(pendingMarkers)) removeMarker(panes[role], m);
      g.pending = {};
      pendingMarkers = {};
      renderPairs();
    } else if (g.pairs.length) {
      dropPair(g.pairs.length - 1);
    }
  });
  sendPairs.addEventListener("click", () => {
    const point_pairs = {
      source: g.pairs.map((p) => fileCoords("source", p.source)),
      target: g.pairs.map((p) => fileCoords("target", p.target)),
    };
    const file = `cat > pairs.json <<'EOF'\n${JSON.stringify(point_pairs)}\nEOF\n`;
    submit({ point_pairs }, "--pairs pairs.json", file);
  });
  renderPairs();

  // Up axes: choosing one turns that model's views to show it up (a check before sending).
  const upSource = el("up-source");
  const upTarget = el("up-target");
  upSource.value = guide.up.source;
  upTarget.value = guide.up.target;
  const internalUp = (role, axis) => new THREE.Vector3(...rotateBack(guide.to_file[role], AXES[axis]));
  const turn = () => {
    panes.source.up = internalUp("source", upSource.value);
    panes.target.up = panes.overlay.up = internalUp("target", upTarget.value);
    redraw();
  };
  upSource.addEventListener("change", turn);
  upTarget.addEventListener("change", turn);
  // Fronts (optional, both or neither): which way each model faces, sent as front_axes with the
  // up axes. One along its own up says nothing about the turn about it: refused here, as the
  // library would refuse it.
  const frontSource = el("front-source");
  const frontTarget = el("front-target");
  const frontError = el("front-error");
  const showFrontError = (message) => {
    frontError.textContent = message;
    frontError.hidden = !message;
    for (const s of [frontSource, frontTarget]) s.setAttribute("aria-invalid", String(Boolean(message)));
  };
  const sameLine = (a, b) => a.slice(1) === b.slice(1); // "+y" and "-y": one axis
  function fronts() {
    const given = [frontSource.value, frontTarget.value];
    if (!given[0] && !given[1]) return null;
    if (!given[0] || !given[1]) return showFrontError("give both fronts (the source's and the target's), or neither");
    const role = sameLine(given[0], upSource.value) ? "source" : sameLine(given[1], upTarget.value) ? "target" : null;
    if (role) return showFrontError(`the ${role} front is along its up axis: choose an axis across it`);
    return given.map((axis) => AXES[axis]);
  }
  for (const s of [frontSource, frontTarget, upSource, upTarget]) s.addEventListener("change", () => showFrontError(""));
  el("up-submit").addEventListener("click", () => {
    const up_axes = [AXES[upSource.value], AXES[upTarget.value]];
    const vectors = (pair) => `${pair[0].join(",")}:${pair[1].join(",")}`;
    const front_axes = fronts();
    if (front_axes === undefined) return; // nothing sent: the message says why
    showFrontError("");
    if (front_axes === null) submit({ up_axes }, `--up ${vectors(up_axes)}`);
    else submit({ up_axes, front_axes }, `--up ${vectors(up_axes)} --front ${vectors(front_axes)}`);
  });

  return (pane, x, y) => {
    if (!g.picking) return;
    const role = pane.name;
    if (role !== "source" && role !== "target") {
      pickState.textContent = "pick on the source or the target view (the overlay is for checking)";
      return;
    }
    place(pane);
    const p = nearestSplat(pane, bytesOf[role], x, y);
    if (!p) {
      pickState.textContent = `no point of the ${role} there: click on the model`;
      return;
    }
    if (pendingMarkers[role]) removeMarker(pane, pendingMarkers[role]);
    g.pending[role] = p;
    pendingMarkers[role] = addMarker(pane, p, PAIR_COLOURS[g.pairs.length % PAIR_COLOURS.length]);
    if (g.pending.source && g.pending.target) {
      g.pairs.push(g.pending);
      markers.push(pendingMarkers);
      g.pending = {};
      pendingMarkers = {};
    }
    renderPairs();
  };
}
