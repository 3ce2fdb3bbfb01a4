// The page's side of the API (README: "Serving"). No framework, no build step.
"use strict";

const token = new URLSearchParams(location.hash.slice(1)).get("token");
const $ = (id) => document.getElementById(id);

function authed(url) {
  return token ? url + (url.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token) : url;
}

async function api(path, opts = {}) {
  const headers = Object.assign({}, opts.headers || {});
  if (token) headers["Authorization"] = "Bearer " + token;
  let r;
  try {
    r = await fetch(path, Object.assign({}, opts, { headers }));
  } catch (e) {
    throw new Error("cannot reach the server (" + e.message + ")");
  }
  if (!r.ok) {
    let msg = r.status + " " + r.statusText;
    try { msg = (await r.json()).error || msg; } catch (_) { /* not JSON */ }
    if (r.status === 503 || r.status === 429) {
      const wait = r.headers.get("Retry-After");
      if (wait) msg += " (the server asks to wait " + wait + " s)";
    }
    throw new Error(msg);
  }
  return r;
}

function took(ms) {
  return ms < 1000 ? Math.round(ms) + " ms" : (ms / 1000).toFixed(1) + " s";
}

function showError(text) {
  const m = $("message");
  m.textContent = text;
  m.hidden = !text;
}

const state = { id: null, size: 0, yaw: 0, pitch: 0, inFlight: false, dirty: false, frameUrl: null };

async function health() {
  try {
    const h = await (await api("/v1/health")).json();
    $("model").textContent = "model: " + h.model + " (" + h.image_size + " px), FLAME: " + h.flame +
      ", rendering on " + h.device + ", batches of up to " + h.max_batch;
  } catch (e) {
    showError(e.message);
  }
}

async function upload(file) {
  showError("");
  if (!file) return;
  $("status").textContent = "Tracking the face and building the avatar…";
  $("busy").hidden = false;
  $("avatar-panel").hidden = true;
  $("video-panel").hidden = true;
  const t0 = performance.now();
  try {
    const r = await api("/v1/avatars", { method: "POST", body: file });
    const a = await r.json();
    state.id = a.id;
    state.size = a.image_size;
    $("crop").src = authed("/v1/avatars/" + a.id + "/crop.png");
    $("crop").hidden = false;
    $("drop-text").textContent = "Drop another photo to start again";
    $("ply").href = authed("/v1/avatars/" + a.id + "/avatar.ply");
    resetControls();
    await renderNow();
    $("status").textContent = (a.cached ? "Found this photo's avatar in memory" :
      "Tracked in " + took(a.track_ms) + ", reconstructed in " + took(a.reconstruct_ms)) +
      "; first frame after " + took(performance.now() - t0) + ".";
    $("avatar-panel").hidden = false;
    $("video-panel").hidden = false;
  } catch (e) {
    $("status").textContent = "";
    showError(e.message);
  } finally {
    $("busy").hidden = true;
  }
}

function controls() {
  const v = (k) => parseFloat(document.querySelector('[data-k="' + k + '"]').value);
  const g = v("gaze");
  return {
    expression: [v("exp0"), v("exp1"), v("exp2"), v("exp3")],
    jaw: [v("jaw"), 0, 0],
    eyes: [0, g, 0, 0, g, 0],
    yaw: state.yaw,
    pitch: state.pitch,
    format: "png",
  };
}

function resetControls() {
  document.querySelectorAll("#sliders input").forEach((i) => { i.value = 0; });
  state.yaw = 0;
  state.pitch = 0;
}

// One request at a time; the newest controls win.
async function renderNow() {
  if (!state.id) return;
  if (state.inFlight) { state.dirty = true; return; }
  state.inFlight = true;
  try {
    do {
      state.dirty = false;
      const r = await api("/v1/avatars/" + state.id + "/render", {
        method: "POST",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify(controls()),
      });
      const url = URL.createObjectURL(await r.blob());
      const img = $("frame");
      await new Promise((ok) => { img.onload = ok; img.onerror = ok; img.src = url; });
      if (state.frameUrl) URL.revokeObjectURL(state.frameUrl);
      state.frameUrl = url;
      img.dataset.renders = String(1 + parseInt(img.dataset.renders || "0", 10));
    } while (state.dirty);
  } catch (e) {
    showError(e.message);
  } finally {
    state.inFlight = false;
  }
}

function setupDrop() {
  const drop = $("drop");
  $("file").addEventListener("change", (e) => upload(e.target.files[0]));
  ["dragenter", "dragover"].forEach((t) => drop.addEventListener(t, (e) => {
    e.preventDefault(); drop.classList.add("over");
  }));
  ["dragleave", "drop"].forEach((t) => drop.addEventListener(t, (e) => {
    e.preventDefault(); drop.classList.remove("over");
  }));
  drop.addEventListener("drop", (e) => upload(e.dataTransfer.files[0]));
}

function setupView() {
  const img = $("frame");
  let drag = null;
  img.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, yaw: state.yaw, pitch: state.pitch };
    img.setPointerCapture(e.pointerId);
    img.classList.add("dragging");
  });
  img.addEventListener("pointermove", (e) => {
    if (!drag) return;
    state.yaw = Math.max(-60, Math.min(60, drag.yaw + (e.clientX - drag.x) * 0.3));
    state.pitch = Math.max(-30, Math.min(30, drag.pitch + (e.clientY - drag.y) * 0.2));
    renderNow();
  });
  const end = () => { drag = null; img.classList.remove("dragging"); };
  img.addEventListener("pointerup", end);
  img.addEventListener("pointercancel", end);
  document.querySelectorAll("#sliders input").forEach((i) => i.addEventListener("input", renderNow));
  $("reset").addEventListener("click", () => { resetControls(); renderNow(); });
}

async function reenact(file) {
  showError("");
  if (!file || !state.id) return;
  const bar = $("job-bar");
  const progress = $("job-progress");
  $("videos").hidden = true;
  $("result-download").hidden = true;
  $("job-status").textContent = "Uploading the video…";
  bar.hidden = false;
  progress.style.width = "0%";
  try {
    const r = await api("/v1/avatars/" + state.id + "/reenact", { method: "POST", body: file });
    const job = await r.json();
    for (;;) {
      await new Promise((ok) => setTimeout(ok, 400));
      const s = await (await api(job.status)).json();
      const frac = s.total ? s.done / s.total : 0;
      const part = s.state === "rendering" ? 0.5 + 0.5 * frac : 0.5 * frac;
      progress.style.width = (100 * part).toFixed(0) + "%";
      $("job-status").textContent = s.state === "rendering" ?
        "Rendering frame " + s.done + " of " + s.total + "…" :
        "Tracking the video (" + s.stage + (s.total ? ", " + s.done + "/" + s.total : "") + ")…";
      if (s.state === "done") break;
      if (s.state === "failed" || s.state === "cancelled") throw new Error("the video could not be reenacted: " + (s.error || s.state));
    }
    const blob = await (await api(job.result)).blob();
    const url = URL.createObjectURL(blob);
    $("source-video").src = URL.createObjectURL(file);
    $("result-video").src = url;
    $("videos").hidden = false;
    await Promise.all([$("source-video").play().catch(() => {}), $("result-video").play().catch(() => {})]);
    const dl = $("result-download");
    dl.href = url;
    dl.download = "reenact.mp4";
    dl.hidden = false;
    $("job-status").textContent = "Done: the driver and the avatar, side by side.";
    progress.style.width = "100%";
  } catch (e) {
    $("job-status").textContent = "";
    bar.hidden = true;
    showError(e.message);
  }
}

// Live driving: camera frames go to the server over a WebSocket, one at a time; each answer is
// the avatar with the expression, jaw, eyes and head pose tracked in that frame.
let cam = null;

function stopWebcam() {
  if (!cam) return;
  const c = cam;
  cam = null;
  c.stream.getTracks().forEach((t) => t.stop());
  if (c.ws.readyState <= 1) c.ws.close();
  $("cam").hidden = true;
  $("webcam").textContent = "Drive with my webcam";
  $("live-status").textContent = "";
}

async function startWebcam() {
  showError("");
  if (!state.id) return;
  let stream;
  try {
    stream = await navigator.mediaDevices.getUserMedia({ video: { width: 640, height: 480 } });
  } catch (e) {
    showError("cannot open the webcam: " + e.message);
    return;
  }
  const video = $("cam");
  video.srcObject = stream;
  video.hidden = false;
  await video.play().catch(() => {});
  const proto = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(authed(proto + "//" + location.host + "/v1/avatars/" + state.id + "/live"));
  ws.binaryType = "blob";
  cam = { stream, ws };
  $("webcam").textContent = "Stop the webcam";
  $("live-status").textContent = "starting…";
  const canvas = document.createElement("canvas");
  const send = () => {
    if (!cam || ws.readyState !== 1 || !video.videoWidth) {
      if (cam && ws.readyState === 1) setTimeout(send, 50);
      return;
    }
    canvas.width = video.videoWidth;
    canvas.height = video.videoHeight;
    canvas.getContext("2d").drawImage(video, 0, 0);
    canvas.toBlob((b) => { if (cam && ws.readyState === 1 && b) ws.send(b); }, "image/jpeg", 0.85);
  };
  ws.onopen = send;
  ws.onmessage = (ev) => {
    if (typeof ev.data === "string") {
      const m = JSON.parse(ev.data);
      $("live-status").textContent = m.error ? m.error : "no face in the camera";
    } else {
      const img = $("frame");
      const url = URL.createObjectURL(ev.data);
      img.onload = () => URL.revokeObjectURL(url);
      img.src = url;
      img.dataset.live = String(1 + parseInt(img.dataset.live || "0", 10));
      $("live-status").textContent = "live";
    }
    send();
  };
  ws.onerror = () => showError("the live connection failed");
  ws.onclose = () => stopWebcam();
}

setupDrop();
setupView();
$("webcam").addEventListener("click", () => (cam ? stopWebcam() : startWebcam()));
$("video-file").addEventListener("change", (e) => reenact(e.target.files[0]));
health();
