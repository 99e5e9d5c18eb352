// diff4splat 4D viewer: the page half of diff4splat/io/viewer_page.py (docs/DESIGN.md, "Viewer").
//
// Reads what diff4splat/io/viewer_page.py embedded in viewer.html (or, under `diff4splat view`, fetches the
// full-size data): the canonical Gaussians as INRIA PLY bytes (colours, opacities, SH) and, for a scene that changes
// with time, each Gaussian's time mean and standard deviation (temporal support) and, for a deforming scene,
// absolute per-keyframe means/quats(wxyz)/scales computed in Python by DynamicGaussians.at(), only at the keys each
// Gaussian needs (none for one that does not move, those around its window for bounded support). The page never
// re-implements the deformation: between two keyframes it interpolates as the renderer interpolates the
// deformation (means linearly, quaternions by nlerp, scales geometrically: s·exp(Δs) with Δs linear), evaluates
// the temporal opacity (o·exp(−½((t − μ_t)/σ_t)²), or o times the trapezoid of the ramps), and writes the result
// into Spark's PackedSplats with setSplat + needsUpdate.
//
// Conventions: the scene's world and cameras.json use OpenCV world-to-camera matrices (x right, y down,
// z forward); three.js cameras are OpenGL (x right, y up, looking down −z), so c2w_gl = inv(viewmat) ·
// diag(1, −1, −1, 1). The projection matrix is built from K (fx, fy, cx, cy in pixels), not from a fov.
import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { SparkRenderer, SplatMesh, SplatFileType } from "@sparkjsdev/spark";

const state = { ready: false, error: null, numGaussians: 0, time: 0, frames: 0, playing: false, renders: 0 };
window.d4s = state;
window.addEventListener("error", (e) => { state.error = String(e.message || e); });
window.addEventListener("unhandledrejection", (e) => { state.error = String(e.reason); });

function bytesOf(id) {
  const text = document.getElementById(id).textContent.trim();
  const bin = atob(text);
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  return out;
}

// IEEE half → float, through a 65536-entry table.
const HALF = (() => {
  const t = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, m = h & 0x3ff;
    t[h] = e === 0 ? s * 2 ** -14 * (m / 1024) : e === 31 ? (m ? NaN : s * Infinity) : s * 2 ** (e - 15) * (1 + m / 1024);
  }
  return t;
})();

// The held keyframes as loaded, without a copy: a Float32Array or (float16) Uint16Array view of the bytes, read
// value by value (float16 through the HALF table): a paper-size scene's keyframes (1.3 M Gaussians × 49 frames,
// 1.3 GB in float16) decoded all at once took 2.6 GB more, on top of the bytes.
function keyframeArray(bytes, dtype) {
  const size = dtype === "float32" ? 4 : 2;
  const b = bytes.byteOffset % size ? bytes.slice() : bytes;  // a typed view needs an aligned offset
  return dtype === "float32" ? new Float32Array(b.buffer, b.byteOffset, b.byteLength / 4)
    : new Uint16Array(b.buffer, b.byteOffset, b.byteLength / 2);
}

// Frame data layout (little endian; diff4splat/io/viewer_data.py encode_keyframes): when cfg.temporal, the time
// means (N), the time scales (N) and, when cfg.temporalRamps, the trapezoid ramps (N) as float32; then, with key
// times (cfg.times), each Gaussian's key window, first key (N) and count (N) as uint16, and the held keyframes
// Gaussian by Gaussian, key by key: means (3), quats (4, wxyz), scales (3) in cfg.dtype. A Gaussian holding no key
// does not move: its pose is the PLY's.
function splitFrames(bytes, cfg) {
  const n = cfg.numGaussians;
  let temporal = null, rest = bytes;
  const aligned = (b, len) => (b.byteOffset % 4 ? b.slice(0, len) : b);  // typed views need aligned offsets
  if (cfg.temporal) {
    const k = cfg.temporalRamps ? 3 : 2;
    const b = aligned(bytes, 4 * k * n);
    const support = new Float32Array(b.buffer, b.byteOffset, k * n);
    temporal = { means: support.subarray(0, n), scales: support.subarray(n, 2 * n),
                 ramps: cfg.temporalRamps ? support.subarray(2 * n, 3 * n) : null };
    rest = bytes.subarray(4 * k * n);
  }
  if (!cfg.times.length) return { temporal, keys: null };
  const w = aligned(rest, 4 * n), windows = new Uint16Array(w.buffer, w.byteOffset, 2 * n);
  const first = windows.subarray(0, n), count = windows.subarray(n, 2 * n), start = new Uint32Array(n);
  for (let i = 1; i < n; i++) start[i] = start[i - 1] + count[i - 1];
  const values = keyframeArray(rest.subarray(4 * n), cfg.dtype);
  return { temporal, keys: { first, count, start, values, half: cfg.dtype !== "float32" } };
}

function projectionFromK(K, w, h, near, far) {
  const [fx, , cx, , fy, cy] = K;
  const m = new THREE.Matrix4();
  m.set(2 * fx / w, 0, 1 - 2 * cx / w, 0,
        0, 2 * fy / h, 2 * cy / h - 1, 0,
        0, 0, -(far + near) / (far - near), -2 * far * near / (far - near),
        0, 0, -1, 0);
  return m;
}

function glPose(viewmat) {  // viewmat: 16 numbers, row-major OpenCV world-to-camera → OpenGL camera-to-world
  const w2c = new THREE.Matrix4().set(...viewmat);
  const c2w = w2c.clone().invert().multiply(new THREE.Matrix4().makeScale(1, -1, -1));
  const pos = new THREE.Vector3(), quat = new THREE.Quaternion(), scl = new THREE.Vector3();
  c2w.decompose(pos, quat, scl);
  const up = new THREE.Vector3(0, 1, 0).applyQuaternion(quat);
  const fwd = new THREE.Vector3(0, 0, -1).applyQuaternion(quat);
  return { pos, quat, up, fwd };
}

async function loadData(cfg) {
  if (cfg.fullUrl && location.protocol.startsWith("http")) {  // served by `diff4splat view`: the full scene
    const get = (name) => fetch(cfg.fullUrl + name).then((r) => {
      if (!r.ok) throw new Error(`viewer: ${cfg.fullUrl + name}: HTTP ${r.status}`);
      return r.arrayBuffer();
    });
    const [ply, frames] = await Promise.all([get("scene.ply"), cfg.dynamic ? get("frames.bin") : null]);
    return { cfg, ply: new Uint8Array(ply), frames: frames && new Uint8Array(frames) };
  }
  return { cfg, ply: bytesOf("d4s-ply"), frames: cfg.dynamic ? bytesOf("d4s-frames") : null };
}

async function main() {
  const { cfg, ply, frames: frameBytes } = await loadData(JSON.parse(document.getElementById("d4s-config").textContent));
  state.config = cfg;
  const view = document.getElementById("view");
  const renderer = new THREE.WebGLRenderer({ canvas: view, antialias: false, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  const bg = cfg.background || [0, 0, 0];  // the colour behind the Gaussians, as the CPU renderer composites it
  renderer.setClearColor(new THREE.Color().setRGB(bg[0], bg[1], bg[2], THREE.SRGBColorSpace), 1);
  const scene = new THREE.Scene();
  // Our renderer's conventions: the scene's screen-space dilation (meta.json eps2d, in pixels² of the output
  // frames; 0.3 by default, 0.1 for a photo layer) added to the 2D covariance without changing opacities (the classic
  // 3DGS rasterization that made the frames: Spark's preBlurAmount, set in resize() in pixels² of the canvas; its
  // blurAmount, 0.3 px² by default, is the antialiased mode's filter that also scales opacities down, which would
  // turn the opaque photo layer translucent: off), 3σ support, alpha ≥ 1/255, and Gaussians sorted by view-space z
  // as 3DGS does (Spark's default sorts by distance from the eye).
  const eps2d = typeof cfg.eps2d === "number" ? cfg.eps2d : 0.3;
  const spark = new SparkRenderer({
    renderer, preBlurAmount: eps2d, blurAmount: 0, maxStdDev: 3.0, minAlpha: 1 / 255, sortRadial: false,
  });
  scene.add(spark);
  const splats = new SplatMesh({ fileBytes: ply, fileType: SplatFileType.PLY, lod: false });
  scene.add(splats);
  await splats.initialized;
  const packed = splats.packedSplats;
  const n = packed.numSplats;
  if (n !== cfg.numGaussians) throw new Error(`viewer: PLY has ${n} Gaussians, config says ${cfg.numGaussians}`);
  state.numGaussians = n;

  const cams = cfg.cameras, W = cfg.width, H = cfg.height;
  const camera = new THREE.PerspectiveCamera(50, W / H, cfg.near, cfg.far);
  let current = 0;  // the path camera last chosen: its K is the projection
  function resize() {
    const s = Math.min(window.innerWidth / W, (window.innerHeight - document.getElementById("ui").offsetHeight) / H);
    const w = Math.max(1, Math.floor(W * s)), h = Math.max(1, Math.floor(H * s));
    renderer.setSize(w, h, true);
    // The canvas shows the output frames magnified w / W times: the dilation scales with it (pixels² of the output →
    // of the canvas), so the photo layer's colours, solved at the output resolution with eps2d, stay exact in a
    // larger window instead of sharpening and ringing; in a smaller one it stays eps2d canvas pixels² (a low-pass
    // against aliasing, as at the output's size).
    spark.preBlurAmount = eps2d * Math.max(1, (w / W) * (h / H));
    // K at the canvas size: scale focal lengths and principal point with the image
    const k = cams[current].K.map((v, i) => (i === 0 || i === 2 ? v * w / W : i === 4 || i === 5 ? v * h / H : v));
    camera.projectionMatrix.copy(projectionFromK(k, w, h, cfg.near, cfg.far));
    camera.projectionMatrixInverse.copy(camera.projectionMatrix).invert();
  }
  let controls = null;
  function goTo(index) {
    const p = glPose(cams[index].viewmat);
    camera.up.copy(p.up);
    // OrbitControls takes its orbit axis from camera.up when it is built (three.js r187): new controls for each
    // camera orbit about that camera's up, not the default +y (mirrored drags in our y-down world, tumbling in a
    // z-up one).
    controls?.dispose();
    controls = new OrbitControls(camera, view);
    current = index;
    resize();
    camera.position.copy(p.pos);
    camera.quaternion.copy(p.quat);
    controls.target.copy(p.pos).addScaledVector(p.fwd, cfg.targetDistance);
    controls.update();
    camera.quaternion.copy(p.quat);  // keep the exact pose (controls.update re-aims at the target, the same direction)
  }
  document.getElementById("ui").hidden = false;
  resize();
  goTo(0);
  window.addEventListener("resize", resize);

  // per-Gaussian colour, opacity and (for a scene with temporal support only) pose as loaded: setSplat rewrites
  // all of a splat's packed fields
  const data = cfg.dynamic ? splitFrames(frameBytes, cfg) : null;
  const keys = data && data.keys;
  const colors = [], opac = new Float32Array(n);
  // the PLY's pose is kept only where a Gaussian holds no keyframe (a still one, or temporal support alone): 40
  // bytes a Gaussian otherwise unused
  const needCanon = data && (!keys || keys.count.some((c) => c === 0));
  const canon = needCanon
    ? { means: new Float32Array(3 * n), quats: new Float32Array(4 * n), scales: new Float32Array(3 * n) } : null;
  for (let i = 0; i < n; i++) {
    const s = packed.getSplat(i);
    colors.push(s.color.clone());
    opac[i] = s.opacity;
    if (canon) {
      canon.means.set([s.center.x, s.center.y, s.center.z], 3 * i);
      canon.quats.set([s.quaternion.w, s.quaternion.x, s.quaternion.y, s.quaternion.z], 4 * i);
      canon.scales.set([s.scales.x, s.scales.y, s.scales.z], 3 * i);
    }
  }
  // The key times around t and the weight of the second: DynamicGaussians.deformation_at's clamped lookup.
  function bracket(t) {
    const ts = cfg.times;
    if (!keys) return { k: 0, k1: 0, w: 0 };
    let k = 0;
    while (k < ts.length - 2 && t > ts[k + 1]) k++;
    const k1 = Math.min(k + 1, ts.length - 1);
    const w = k1 === k ? 0 : Math.min(1, Math.max(0, (t - ts[k]) / (ts[k1] - ts[k])));
    return { k, k1, w };
  }
  const c = new THREE.Vector3(), sc = new THREE.Vector3(), q = new THREE.Quaternion();
  const ka = new Float32Array(10), kb = new Float32Array(10);
  // Gaussian i's pose at key k into out (means, quats wxyz, scales): its held key nearest to k (outside its window
  // it is not seen), or the PLY's for a Gaussian that holds none.
  function poseAt(i, k, out) {
    const m = keys ? keys.count[i] : 0;
    if (m === 0) {
      for (let j = 0; j < 3; j++) { out[j] = canon.means[3 * i + j]; out[7 + j] = canon.scales[3 * i + j]; }
      for (let j = 0; j < 4; j++) out[3 + j] = canon.quats[4 * i + j];
      return;
    }
    const o = 10 * (keys.start[i] + Math.min(m - 1, Math.max(0, k - keys.first[i]))), v = keys.values;
    if (keys.half) for (let j = 0; j < 10; j++) out[j] = HALF[v[o + j]];
    else for (let j = 0; j < 10; j++) out[j] = v[o + j];
  }
  // Gaussian i at time t between key times k and k1 (weight w of k1) into c, q, sc; returns its opacity.
  function splatAt(k, k1, w, t, i) {
    poseAt(i, k, ka);
    poseAt(i, k1, kb);
    c.set(ka[0] + w * (kb[0] - ka[0]), ka[1] + w * (kb[1] - ka[1]), ka[2] + w * (kb[2] - ka[2]));
    // s·exp((1 − w)·Δs_a + w·Δs_b) = s_a^(1−w) · s_b^w (a float16 scale rounded to 0 falls back to linear)
    const geo = (x, y) => (x > 0 && y > 0 ? x * Math.pow(y / x, w) : x + w * (y - x));
    sc.set(geo(ka[7], kb[7]), geo(ka[8], kb[8]), geo(ka[9], kb[9]));
    // nlerp on the shorter arc; wxyz in the data, THREE.Quaternion is (x, y, z, w)
    const d = ka[3] * kb[3] + ka[4] * kb[4] + ka[5] * kb[5] + ka[6] * kb[6];
    const sb = d < 0 ? -w : w, sa = 1 - w;
    q.set(sa * ka[4] + sb * kb[4], sa * ka[5] + sb * kb[5], sa * ka[6] + sb * kb[6], sa * ka[3] + sb * kb[3]).normalize();
    return opacityAt(t, i);
  }
  // Gaussian i's opacity at time t: o, or o times its temporal support.
  function opacityAt(t, i) {
    const tp = data.temporal;
    if (!tp) return opac[i];
    if (tp.ramps) {  // the trapezoid clamp((σ_t − |t − μ_t|)/r_t, 0, 1); r_t = 0: a box open at its ends
      const inside = tp.scales[i] - Math.abs(t - tp.means[i]);
      return opac[i] * (tp.ramps[i] > 0 ? Math.min(1, Math.max(0, inside / tp.ramps[i])) : (inside > 0 ? 1 : 0));
    }
    const z = (t - tp.means[i]) / tp.scales[i];
    return opac[i] * Math.exp(-0.5 * z * z);
  }
  // The opacity last written into Spark's splat i (−1: never): a Gaussian unseen then and now, or one that holds no
  // keyframe and has no temporal support (its pose and opacity never change), is not written again.
  const written = new Float32Array(n).fill(-1);
  function setTime(t) {
    state.time = t;
    if (!data) return;
    const { k, k1, w } = bracket(t);
    for (let i = 0; i < n; i++) {
      if (written[i] >= 0) {
        if (!data.temporal && keys && keys.count[i] === 0) continue;
        if (written[i] === 0 && opacityAt(t, i) === 0) continue;
      }
      const o = splatAt(k, k1, w, t, i);
      packed.setSplat(i, c, sc, q, o, colors[i]);
      written[i] = o;
    }
    packed.needsUpdate = true;
    splats.updateVersion?.();
  }
  // For tests: Gaussian i at time t as setTime writes it, before Spark packs it.
  state.splatAt = (t, i) => {
    if (!data) return null;  // a scene that does not change with time keeps the PLY's Gaussians
    const { k, k1, w } = bracket(t), o = splatAt(k, k1, w, t, i);
    return { mean: c.toArray(), quat: [q.w, q.x, q.y, q.z], scale: sc.toArray(), opacity: o };
  };
  // For tests: Gaussian i as Spark holds it now (packed: centre float16, opacity 8-bit).
  state.packedSplat = (i) => {
    const s = packed.getSplat(i);
    return { mean: [s.center.x, s.center.y, s.center.z], opacity: s.opacity };
  };
  // For tests: the view camera's pose (three.js, OpenGL axes) and the orbit's target.
  state.pose = () => ({ position: camera.position.toArray(), quaternion: camera.quaternion.toArray(),
                        up: camera.up.toArray(), target: controls.target.toArray() });

  // UI: time slider + play/pause for a dynamic scene only; the path cameras; the frame time
  const ui = document.getElementById("ui");
  const camSelect = document.getElementById("camera");
  cams.forEach((cam, i) => {
    const o = document.createElement("option");
    o.value = String(i);
    o.textContent = `camera ${i}` + (cfg.dynamic && cam.time !== undefined ? ` (t = ${cam.time.toFixed(3)})` : "");
    camSelect.appendChild(o);
  });
  const slider = document.getElementById("time"), play = document.getElementById("play"), label = document.getElementById("tlabel");
  const [t0, t1] = cfg.dynamic ? cfg.timeRange : [0, 0];
  const showTime = (t) => { label.textContent = `t = ${t.toFixed(3)} (${(t * cfg.duration).toFixed(2)} s)`; };
  camSelect.addEventListener("change", () => {
    const i = Number(camSelect.value);
    goTo(i);
    if (cfg.dynamic && cams[i].time !== undefined) { setTime(cams[i].time); slider.value = String(Math.round(1000 * (cams[i].time - t0) / Math.max(t1 - t0, 1e-9))); showTime(cams[i].time); }
  });
  if (cfg.dynamic) {
    slider.addEventListener("input", () => { const t = t0 + (t1 - t0) * Number(slider.value) / 1000; setTime(t); showTime(t); });
    play.addEventListener("click", () => { state.playing = !state.playing; play.textContent = state.playing ? "pause" : "play"; });
    setTime(t0);
    showTime(t0);
  } else {
    document.getElementById("timecontrols").remove();
  }
  if (cfg.note) document.getElementById("note").textContent = cfg.note;
  resize();  // the controls' final height

  let last = performance.now(), warm = 0;
  state.setTime = (t) => {
    setTime(t);
    if (cfg.dynamic) { slider.value = String(Math.round(1000 * (t - t0) / Math.max(t1 - t0, 1e-9))); showTime(t); }
  };
  state.goTo = goTo;
  renderer.setAnimationLoop((now) => {
    if (state.playing && cfg.dynamic) {
      let t = state.time + (now - last) / 1000 / Math.max(cfg.duration, 1e-6);
      if (t > t1) t = t0 + (t - t1);
      setTime(t);
      slider.value = String(Math.round(1000 * (t - t0) / Math.max(t1 - t0, 1e-9)));
      showTime(t);
    }
    last = now;
    controls.update();
    renderer.render(scene, camera);
    state.renders++;
    if (!state.ready && ++warm >= 10) state.ready = true;  // Spark sorts in a worker: let a few frames settle
  });
}

main().catch((e) => { state.error = String(e && e.stack || e); document.getElementById("note").textContent = "viewer error: " + e; });
