// FastGHA browser demo: plain JS, no build step. Protocol: docs/protocol.md.
//
// Flow: load 1-8 photos (+ cameras.json, + masks; or a shipped sample) -> POST /v1/avatars with
// "Prefer: respond-async" (202: a creation job) -> poll /v1/avatars/{id}/status, showing the
// job's stage and progress -> WebSocket /v1/avatars/{id}/stream once it is ready. Photos without
// cameras.json are tracked by the server. Requests are sent latest-wins: at most one request in
// flight; while it renders, UI changes only mark the state dirty, and the newest state is sent
// when the frame arrives. So the server is never flooded and the picture follows the sliders.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const MAIN_NAMES = [  // ict53 names shown by default (the rest behind "more…")
    "jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthSmile_L", "mouthSmile_R", "browInnerUp_L", "browInnerUp_R",
    "browDown_L", "browDown_R", "mouthFunnel", "mouthPucker", "cheekPuff_L", "cheekPuff_R", "eyeWide_L", "eyeWide_R",
  ];
  const MAX_MAIN = 16;  // every name above: cheekPuff_L and cheekPuff_R (and each other pair) stay together
  const FATAL_CLOSE = {  // close codes where reconnecting with the same token cannot help
    4401: "the avatar token was refused", 4404: "the avatar no longer exists", 4409: "the avatar was made by another model",
    4429: "too many messages", 1009: "message too large",
  };
  const CAM_DEFAULT = { yaw: 0, pitch: 0, radius: 1.0, fov: 20 };

  // ------------------------------------------------------------------ state (one object, inspectable in tests)
  const S = {
    model: null,            // GET /v1/model
    inputs: null,           // {images: [File|Blob], masks: [..]|null, cameras: [..]|null (the server tracks), camerasFrom, head: {..}|null}
    sequence: null,         // [[E numbers], ...] from the sample's expressions
    avatar: null,           // {avatar_id, token, ...}
    job: null,              // the creation job being watched: {avatar_id, token, status, stage, progress, ...}
    progressLog: [],        // every job status shown, for tests: [{status, stage, progress, queue_position}]
    values: {},             // expression name -> weight
    cam: { ...CAM_DEFAULT },
    size: 256,
    ws: null, wsWanted: false, reconnectAttempt: 0, reconnectTimer: null,
    seq: 0, inFlight: null, sentAt: new Map(), dirty: false,
    frames: 0, lastSeq: -1, serverDropped: 0, coalesced: 0, frameTimes: [], latencies: [], lastRenderMs: null,
    drawChain: Promise.resolve(),
    playing: false, playIndex: 0, playTimer: null, orbitPhase: 0, orbitTimer: null,
  };
  window.fastghaDemo = S;

  // ------------------------------------------------------------------ messages
  function say(text, kind = "info") {
    const box = $("messages");
    const last = box.firstElementChild;
    if (last && last.dataset.text === text) {  // the same message again: count it, do not flood the log
      last.dataset.count = String(Number(last.dataset.count || 1) + 1);
      last.textContent = `${new Date().toLocaleTimeString()}  ${text} (×${last.dataset.count})`;
      return;
    }
    const div = document.createElement("div");
    div.className = kind;
    div.dataset.text = text;
    div.textContent = `${new Date().toLocaleTimeString()}  ${text}`;
    box.prepend(div);
    while (box.childElementCount > 60) box.lastChild.remove();
  }
  function setStatus(text) { $("st-status").textContent = text; }

  async function apiError(r) {
    try {
      const j = await r.json();
      if (j && j.error) return `${j.error.code}: ${j.error.message} (HTTP ${r.status})`;
    } catch (_) { /* not JSON */ }
    return `HTTP ${r.status} ${r.statusText}`;
  }

  // ------------------------------------------------------------------ cameras (OpenCV look-at, like fastgha_core/cameras.py)
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const norm = (a) => { const n = Math.hypot(a[0], a[1], a[2]); return [a[0] / n, a[1] / n, a[2] / n]; };

  function lookAtCamera(eye, target, fovDeg, width, height) {
    const z = norm(sub(target, eye));          // forward
    const x = norm(cross([0, -1, 0], z));      // right = down x forward
    const y = cross(z, x);                     // down
    const w2c = [
      [x[0], x[1], x[2], -dot(x, eye)],
      [y[0], y[1], y[2], -dot(y, eye)],
      [z[0], z[1], z[2], -dot(z, eye)],
      [0, 0, 0, 1],
    ];
    const f = 0.5 * height / Math.tan((fovDeg * Math.PI / 180) / 2);
    return { K: [[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], w2c, width, height };
  }

  function currentCamera() {
    const c = S.cam;
    const yaw = (c.yaw + (S.orbitTimer ? 30 * Math.sin(S.orbitPhase) : 0)) * Math.PI / 180;
    const pitch = c.pitch * Math.PI / 180;
    const eye = [c.radius * Math.cos(pitch) * Math.sin(yaw), c.radius * Math.sin(pitch), c.radius * Math.cos(pitch) * Math.cos(yaw)];
    return lookAtCamera(eye, [0, 0, 0], c.fov, S.size, S.size);
  }

  // ------------------------------------------------------------------ model + sliders
  async function loadModel() {
    try {
      const r = await fetch("/v1/model");
      if (!r.ok) throw new Error(await apiError(r));
      S.model = await r.json();
      const m = S.model;
      $("server-info").textContent = `model ${m.name} · ${m.expression_space} (${m.expression_dim}) · ${m.device}`;
      S.size = Math.min(m.max_output_size || 1024, Number($("size").value));
      buildSliders();
    } catch (e) {
      $("server-info").textContent = "server unreachable";
      say(`cannot read the model description: ${e.message}`, "err");
    }
  }

  function buildSliders() {
    const names = S.model.expression_names;
    const lo = S.model.expression_space === "ict53" ? 0 : -1;
    let main = MAIN_NAMES.filter((n) => names.includes(n)).slice(0, MAX_MAIN);
    if (main.length === 0) main = names.slice(0, Math.min(MAX_MAIN, names.length));
    const order = main.concat(names.filter((n) => !main.includes(n)));
    const box = $("sliders");
    box.innerHTML = "";
    for (const name of order) {
      const extra = !main.includes(name);
      const wrap = document.createElement("div");
      wrap.className = extra ? "extra" : "main";
      const label = document.createElement("label");
      label.textContent = name;
      label.htmlFor = `s-${name}`;
      const input = document.createElement("input");
      Object.assign(input, { type: "range", min: String(lo), max: "1", step: "0.01", value: "0", id: `s-${name}` });
      input.dataset.name = name;
      const v = document.createElement("span");
      v.className = "v";
      v.textContent = "0.00";
      input.addEventListener("input", () => {
        S.values[name] = Number(input.value);
        v.textContent = Number(input.value).toFixed(2);
        if (S.playing) stopPlayer();
        markDirty();
      });
      wrap.append(label, input, v);
      box.append(wrap);
      S.values[name] = 0;
    }
  }

  function setSliderValues(values) {
    for (const [name, val] of Object.entries(values)) {
      S.values[name] = val;
      const input = document.getElementById(`s-${name}`);
      if (input) {
        input.value = String(val);
        input.nextElementSibling.textContent = Number(val).toFixed(2);
      }
    }
  }

  $("more-toggle").addEventListener("click", () => {
    const box = $("sliders");
    box.classList.toggle("all");
    $("more-toggle").textContent = box.classList.contains("all") ? "fewer" : "more…";
  });
  $("reset-expr").addEventListener("click", () => {
    stopPlayer();
    setSliderValues(Object.fromEntries(Object.keys(S.values).map((n) => [n, 0])));
    markDirty();
  });

  // ------------------------------------------------------------------ inputs: files and samples
  function showInputs() {
    const t = $("thumbs");
    t.innerHTML = "";
    if (!S.inputs) { $("input-summary").textContent = "nothing loaded"; $("create").disabled = true; return; }
    for (const img of S.inputs.images) {
      const el = document.createElement("img");
      el.src = URL.createObjectURL(img);
      el.title = img.name || "";
      t.append(el);
    }
    const n = S.inputs.images.length;
    const cams = S.inputs.cameras;
    const maxImages = (S.model && S.model.max_images) || 8;
    let problem = "";
    if (n === 0) problem = " — drop 1 to 8 photos";
    else if (n > maxImages) problem = ` — at most ${maxImages} photos`;
    else if (cams && cams.length !== n) problem = ` — cameras.json holds ${cams.length} camera(s) for ${n} photo(s)`;
    $("input-summary").textContent = `${n} photo(s), ` + (cams ? `${cams.length} camera(s)` : "no cameras (the server finds the face)") +
      (S.inputs.masks ? `, ${S.inputs.masks.length} mask(s)` : "") + (S.inputs.head && cams ? ", tracked head" : "") + (S.sequence ? `, ${S.sequence.length}-frame sequence` : "") + problem;
    $("create").disabled = problem !== "" || S.job !== null;
  }

  async function takeFiles(fileList) {
    const files = Array.from(fileList);
    const camFile = files.find((f) => f.name.toLowerCase().endsWith(".json") && f.name.toLowerCase().includes("camera"));
    // the sequence: a JSON named like one, else any JSON but a tracked folder's head.json / info.json
    const jsons = files.filter((f) => f !== camFile && f.name.toLowerCase().endsWith(".json"));
    const seqFile = jsons.find((f) => /expression|sequence|frames/i.test(f.name)) || jsons.find((f) => !/^(head|info)\.json$/i.test(f.name));
    const headFile = jsons.find((f) => /^head\.json$/i.test(f.name));
    const isImg = (f) => /\.(jpe?g|png)$/i.test(f.name);
    const stem = (f) => f.name.replace(/\.[^.]+$/, "");
    const images = files.filter((f) => isImg(f) && !stem(f).endsWith("_mask")).sort((a, b) => a.name.localeCompare(b.name));
    const maskByStem = new Map(files.filter((f) => isImg(f) && stem(f).endsWith("_mask")).map((f) => [stem(f).slice(0, -5), f]));
    const old = S.inputs;
    // new photos keep earlier cameras only when those came from a cameras.json of the user's own
    let cameras = old && (images.length === 0 || old.camerasFrom === "file") ? old.cameras : null;
    let camerasFrom = cameras ? old.camerasFrom : null;
    if (camFile) {
      try {
        let c = JSON.parse(await camFile.text());
        if (c && !Array.isArray(c) && Array.isArray(c.cameras)) c = c.cameras;
        if (!Array.isArray(c)) throw new Error("it must be a JSON array of camera objects");
        cameras = c;
        camerasFrom = "file";
      } catch (e) {  // a broken cameras.json must not throw away the photos dropped with it
        say(`ignored ${camFile.name}: ${e.message}; the photos are kept${images.length ? " (without cameras the server finds the face)" : ""}`, "err");
      }
    }
    let tracked = null;  // expressions.json of `fastgha track`: each crop's expression, by file name
    if (seqFile) {
      try {
        const q = JSON.parse(await seqFile.text());
        if (q && !Array.isArray(q) && Array.isArray(q.images) && Array.isArray(q.expressions)) tracked = q;
        const frames = Array.isArray(q) ? q : q && (q.frames || q.expressions);  // {frames} (samples) or track's expressions.json
        if (!Array.isArray(frames)) throw new Error("expected a list of frames, {frames: [...]} or the expressions.json of `fastgha track`");
        S.sequence = frames;
        $("play").disabled = false;
      } catch (e) {
        say(`ignored ${seqFile.name}: ${e.message}`, "err");
      }
    }
    if (images.length === 0 && !(old && old.images.length)) {
      if (!camFile && !seqFile) say("no photos among the dropped files (JPEG or PNG)", "err");
      if (camFile && cameras) S.inputs = { images: [], masks: null, cameras, camerasFrom, head: null };
      showInputs();
      return;
    }
    const imgs = images.length ? images : old.images;
    const masks = images.length ? (images.every((f) => maskByStem.has(stem(f))) ? images.map((f) => maskByStem.get(stem(f))) : null) : old.masks;
    if (images.length && !camFile && cameras && cameras.length !== imgs.length) {
      // an earlier cameras.json that does not fit the new photos would only block "Create": drop it
      say(`dropped the earlier cameras.json (${cameras.length} camera(s)): it does not fit ${imgs.length} photo(s); ` +
          "without cameras the server finds the face", "info");
      cameras = null;
      camerasFrom = null;
    }
    // a tracked folder's head.json goes with its cameras (docs/protocol.md, the `head` part): the
    // server then puts every pixel's Gaussian on the tracked head, as `fastgha reconstruct` does
    let head = images.length === 0 && old ? old.head || null : null;
    if (headFile) head = await trackedHead(headFile, tracked, imgs, cameras);
    S.inputs = { images: imgs, masks, cameras, camerasFrom, head };
    if (images.length) $("sample-select").value = "";  // the list no longer names what is loaded
    showInputs();
  }

  async function trackedHead(headFile, tracked, imgs, cameras) {
    // head.json + each photo's tracked expression (expressions.json, by file name, else by stem), or null with a message
    try {
      const h = JSON.parse(await headFile.text());
      if (!h || Array.isArray(h) || typeof h !== "object") throw new Error("it must be a JSON object with an identity list");
      if (!cameras) throw new Error("it needs the cameras.json it was tracked with");
      if (!tracked) throw new Error("it needs the expressions.json written with it by `fastgha track`");
      const byName = new Map(tracked.images.map((n, i) => [n, tracked.expressions[i]]));
      const byStem = new Map(tracked.images.map((n, i) => [n.replace(/\.[^.]+$/, ""), tracked.expressions[i]]));
      const expressions = imgs.map((f) => byName.get(f.name) || byStem.get(f.name.replace(/\.[^.]+$/, "")));
      const missing = imgs.filter((f, i) => !expressions[i]).map((f) => f.name);
      if (missing.length) throw new Error(`expressions.json has no expression for ${missing.join(", ")}`);
      // head.json's frames (each crop's photo, by file name) go one per photo, in their order; left out when one is missing
      const { frames: byFile, ...head } = h;
      const frames = byFile && typeof byFile === "object" && !Array.isArray(byFile)
        ? imgs.map((f) => byFile[f.name] || byFile[f.name.replace(/\.[^.]+$/, "") + ".png"]) : null;
      return frames && frames.every(Boolean) ? { ...head, expressions, frames } : { ...head, expressions };
    } catch (e) {
      say(`ignored ${headFile.name}: ${e.message}; the Gaussians follow the network's depth`, "err");
      return null;
    }
  }

  const drop = $("drop");
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => { e.preventDefault(); drop.classList.remove("over"); takeFiles(e.dataTransfer.files); });
  $("file-input").addEventListener("change", (e) => takeFiles(e.target.files));

  async function loadSampleList() {
    try {
      const r = await fetch("/v1/samples");
      if (!r.ok) throw new Error(await apiError(r));
      const { samples } = await r.json();
      const sel = $("sample-select");
      sel.innerHTML = '<option value="">(your own photos)</option>';
      for (const s of samples) {
        const o = document.createElement("option");
        o.value = s.name;
        o.textContent = `${s.name} (${s.images.length} photos${s.has_expressions ? `, ${s.num_expression_frames} frames` : ""})`;
        o.dataset.info = JSON.stringify(s);
        sel.append(o);
      }
      if (samples.length === 0) sel.innerHTML = '<option value="">(no samples shipped)</option>';
      else sel.value = samples[0].name;
      $("load-sample").disabled = samples.length === 0;
    } catch (e) {
      say(`no sample list (${e.message}); drop your own photos and cameras.json`, "info");
    }
  }

  async function fetchOk(url) {
    const r = await fetch(url);
    if (!r.ok) throw new Error(`${url}: ${await apiError(r)}`);
    return r;
  }

  $("load-sample").addEventListener("click", async () => {
    const opt = $("sample-select").selectedOptions[0];
    if (!opt || !opt.value) return;
    const info = JSON.parse(opt.dataset.info);
    const base = `/v1/samples/${encodeURIComponent(info.name)}/`;
    $("load-sample").disabled = true;
    try {
      const images = await Promise.all(info.images.map(async (f) => new File([await (await fetchOk(base + f)).blob()], f)));
      const stems = info.images.map((f) => f.replace(/\.[^.]+$/, ""));
      const maskFor = (s) => info.masks.find((m) => m === `${s}_mask.png` || m === `masks/${s}.png`);
      const masks = info.masks.length && stems.every(maskFor)
        ? await Promise.all(stems.map(async (s) => new File([await (await fetchOk(base + maskFor(s))).blob()], maskFor(s))))
        : null;
      const cameras = await (await fetchOk(base + "cameras.json")).json();
      S.sequence = null;
      if (info.has_expressions) {
        const e = await (await fetchOk(base + "expressions.json")).json();
        S.sequence = e.frames;
        if (e.fps) $("play-fps").value = String(e.fps);
      }
      S.inputs = { images, masks, cameras, camerasFrom: "sample", head: null };
      $("play").disabled = !S.sequence;
      showInputs();
      say(`loaded sample ${info.name}`, "ok");
    } catch (e) {
      say(`could not load the sample: ${e.message}`, "err");
    } finally {
      $("load-sample").disabled = false;
    }
  });

  // ------------------------------------------------------------------ create / delete / PLY
  function showJob(st) {
    // one line under the Create button: the stage, the queue position and a progress bar
    S.progressLog.push({ status: st.status, stage: st.stage, progress: st.progress, queue_position: st.queue_position });
    const pct = Math.round(100 * (st.progress || 0));
    const where = st.queue_position ? ` (position ${st.queue_position} in the queue)` : "";
    $("job-bar").hidden = false;
    $("job-bar").value = st.progress || 0;
    $("recon").textContent = `${st.stage}${where} · ${pct} %`;
  }

  const sleep = (ms) => new Promise((res) => setTimeout(res, ms));

  async function watchJob(job) {
    // poll the status resource until the job is done (the server answers in well under a frame)
    let st = job;
    for (;;) {
      if (S.job !== job) return null;  // superseded (deleted / new avatar)
      showJob(st);
      if (st.status === "ready" || st.status === "failed") return st;
      await sleep(250);
      const r = await fetch(`/v1/avatars/${job.avatar_id}/status`, { headers: { Authorization: `Bearer ${job.token}` } });
      if (!r.ok) throw new Error(await apiError(r));
      st = await r.json();
    }
  }

  $("create").addEventListener("click", async () => {
    if (!S.inputs || S.job) return;
    const fd = new FormData();
    S.inputs.images.forEach((f, i) => fd.append("images", f, f.name || `photo${i + 1}.jpg`));
    if (S.inputs.cameras) fd.append("cameras", JSON.stringify(S.inputs.cameras));
    if (S.inputs.cameras && S.inputs.head) fd.append("head", JSON.stringify(S.inputs.head));
    if (S.inputs.masks) S.inputs.masks.forEach((f, i) => fd.append("masks", f, f.name || `photo${i + 1}_mask.png`));
    const headers = { Prefer: "respond-async" };  // 202 + a status resource instead of waiting (docs/protocol.md)
    const key = $("api-key").value.trim();
    if (key) headers["X-API-Key"] = key;
    $("create").disabled = true;
    $("recon").textContent = "uploading…";
    const t0 = performance.now();
    try {
      const r = await fetch("/v1/avatars", { method: "POST", body: fd, headers });
      if (r.status === 429 || r.status === 503) {
        const wait = r.headers.get("Retry-After");
        throw new Error(`${await apiError(r)}; the server is busy${wait ? `: try again in ${wait} s` : ""}`);
      }
      if (!r.ok) throw new Error(await apiError(r));
      const job = await r.json();
      closeStream();
      S.avatar = null;
      S.job = job;
      $("delete").disabled = false;  // deleting cancels a job that is still running
      say(`avatar ${job.avatar_id} accepted: ${job.status}`, "info");
      const st = r.status === 202 ? await watchJob(job) : { status: "ready", avatar: job };
      if (st === null) return;
      if (st.status === "failed") throw new Error(`${st.error.code}: ${st.error.message} (HTTP ${st.error.status})`);
      const av = { num_images: S.inputs.images.length, ...st.avatar, token: job.token };  // photos sent: view_blend.views beyond them are mirrored
      const rt = performance.now() - t0;
      S.avatar = av;
      $("recon").textContent = `reconstruction ${av.reconstruction_ms.toFixed(0)} ms` + (av.tracking_ms != null ? `, tracking ${av.tracking_ms.toFixed(0)} ms` : "") +
        (av.refining_ms != null ? `, refinement ${av.refining_ms.toFixed(0)} ms` : "") +
        ` (round trip ${rt.toFixed(0)} ms) · ${av.num_gaussians.toLocaleString()} Gaussians` + describeAvatar(av);
      say(`avatar ${av.avatar_id} created`, "ok");
      $("download-ply").disabled = false;
      openStream();
    } catch (e) {
      $("recon").textContent = "";
      if (!S.avatar) $("delete").disabled = true;
      say(`creating the avatar failed: ${e.message}`, "err");
    } finally {
      S.job = null;
      $("job-bar").hidden = true;
      showInputs();
    }
  });

  function authHeaders() { return { Authorization: `Bearer ${S.avatar.token}` }; }

  $("download-ply").addEventListener("click", async () => {
    if (!S.avatar) return;
    try {
      const r = await fetch(`/v1/avatars/${S.avatar.avatar_id}/ply`, { headers: authHeaders() });
      if (!r.ok) throw new Error(await apiError(r));
      const url = URL.createObjectURL(await r.blob());
      const a = Object.assign(document.createElement("a"), { href: url, download: `${S.avatar.avatar_id}.ply` });
      document.body.append(a);
      a.click();
      a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 10000);
    } catch (e) {
      say(`PLY download failed: ${e.message}`, "err");
    }
  });

  $("delete").addEventListener("click", async () => {
    const av = S.avatar || S.job;  // a job still running is cancelled
    if (!av) return;
    closeStream();
    S.avatar = null;
    S.job = null;
    $("download-ply").disabled = true;
    $("delete").disabled = true;
    $("overlay").classList.remove("hidden");
    $("overlay").textContent = "avatar deleted";
    try {
      const r = await fetch(`/v1/avatars/${av.avatar_id}`, { method: "DELETE", headers: { Authorization: `Bearer ${av.token}` } });
      if (!r.ok && r.status !== 404) throw new Error(await apiError(r));
      say(`avatar ${av.avatar_id} deleted`, "ok");
    } catch (e) {
      say(`delete failed: ${e.message}`, "err");
    }
  });

  // ------------------------------------------------------------------ streaming
  function wsUrl() {
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    // browsers cannot set headers on WebSockets: the token goes in the query (docs/protocol.md)
    return `${proto}//${location.host}/v1/avatars/${S.avatar.avatar_id}/stream?token=${encodeURIComponent(S.avatar.token)}`;
  }

  function openStream() {
    if (!S.avatar) return;
    S.wsWanted = true;
    clearTimeout(S.reconnectTimer);
    setStatus(S.reconnectAttempt ? `reconnecting (try ${S.reconnectAttempt})…` : "connecting…");
    const ws = new WebSocket(wsUrl());
    ws.binaryType = "arraybuffer";
    S.ws = ws;
    S.inFlight = null;
    S.sentAt.clear();
    ws.onmessage = (ev) => {
      if (ws !== S.ws) return;
      if (typeof ev.data === "string") onText(ev.data);
      else onFrame(ev.data);
    };
    ws.onclose = (ev) => {
      if (ws !== S.ws) return;
      S.ws = null;
      S.inFlight = null;
      if (!S.wsWanted) { setStatus("closed"); return; }
      const fatal = FATAL_CLOSE[ev.code];
      if (fatal) {
        S.wsWanted = false;
        setStatus("disconnected");
        say(`stream closed (${ev.code} ${ev.reason || ""}): ${fatal}`, "err");
        return;
      }
      const delay = Math.min(8000, 500 * 2 ** S.reconnectAttempt);
      S.reconnectAttempt += 1;
      setStatus(`disconnected — retrying in ${(delay / 1000).toFixed(1)} s`);
      say(`stream disconnected (code ${ev.code}${ev.reason ? ` ${ev.reason}` : ""}); reconnecting in ${(delay / 1000).toFixed(1)} s`, "err");
      S.reconnectTimer = setTimeout(openStream, delay);
    };
    ws.onerror = () => { /* onclose follows with the code */ };
  }

  function closeStream() {
    S.wsWanted = false;
    clearTimeout(S.reconnectTimer);
    if (S.ws) { const ws = S.ws; S.ws = null; ws.close(1000, "client closed"); }
    setStatus("idle");
  }

  const EXPRESSION_ERRORS = new Set(["unknown_expression_name", "invalid_expression", "invalid_expression_length"]);

  function onText(text) {
    let msg;
    try { msg = JSON.parse(text); } catch (_) { say("server sent a message that is not JSON", "err"); return; }
    if (msg.type === "ready") {
      S.reconnectAttempt = 0;
      setStatus("streaming");
      $("overlay").classList.add("hidden");
      say(`stream ready: frames at ${S.size}×${S.size}, ${msg.expression_space}`, "ok");
      markDirty();
    } else if (msg.type === "error") {
      if (EXPRESSION_ERRORS.has(msg.code)) {
        // a sequence with names (or lengths) the server refuses: stop it, and forget the names that
        // have no slider, or every later request (a slider moved) would be refused the same way
        const playing = S.playing;
        if (playing) stopPlayer();
        const known = new Set((S.model && S.model.expression_names) || []);
        for (const k of Object.keys(S.values)) if (!known.has(k)) delete S.values[k];
        say(`${playing ? "stopped the sequence: " : ""}server: ${msg.code}: ${msg.message}`, "err");
      } else {
        say(`server: ${msg.code}: ${msg.message}`, "err");
      }
      // an error answers no frame: release the slot so the stream goes on
      S.inFlight = null;
      if (S.dirty) sendNow();
    }
  }

  function onFrame(buf) {
    const now = performance.now();
    const dv = new DataView(buf);
    if (buf.byteLength < 8 || String.fromCharCode(dv.getUint8(0), dv.getUint8(1), dv.getUint8(2), dv.getUint8(3)) !== "FGHA") {
      say("malformed frame message", "err");
      return;
    }
    const n = dv.getUint32(4, true);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buf, 8, n)));
    const jpeg = new Blob([new Uint8Array(buf, 8 + n)], { type: "image/jpeg" });
    const sent = S.sentAt.get(header.seq);
    for (const k of S.sentAt.keys()) if (k <= header.seq) S.sentAt.delete(k);
    if (sent !== undefined) S.latencies.push(now - sent);
    if (S.latencies.length > 60) S.latencies.shift();
    S.frameTimes.push(now);
    while (S.frameTimes.length && now - S.frameTimes[0] > 2000) S.frameTimes.shift();
    S.serverDropped = header.dropped || 0;
    S.lastRenderMs = header.render_ms;
    if (S.inFlight !== null && header.seq >= S.inFlight) S.inFlight = null;
    if (S.dirty) sendNow();  // latest wins: the newest state goes out as soon as the slot frees
    // decode off the message handler, but draw frames in arrival order
    S.drawChain = S.drawChain.then(async () => {
      try {
        const bmp = await createImageBitmap(jpeg);
        const c = $("frame");
        if (c.width !== bmp.width || c.height !== bmp.height) { c.width = bmp.width; c.height = bmp.height; }
        c.getContext("2d").drawImage(bmp, 0, 0);
        bmp.close();
      } catch (e) {
        say(`could not decode a frame: ${e.message}`, "err");
      }
      S.frames += 1;
      S.lastSeq = header.seq;
    });
  }

  function expressionMessage() {
    // name -> weight map of the non-zero weights; missing names are neutral on the server
    const expr = {};
    for (const [k, v] of Object.entries(S.values)) if (v !== 0) expr[k] = v;
    return expr;
  }

  function markDirty() {
    if (S.dirty) S.coalesced += 1;  // an update replaced by a newer one before it was sent
    S.dirty = true;
    if (S.inFlight === null) sendNow();
  }

  function sendNow() {
    const ws = S.ws;
    if (!ws || ws.readyState !== WebSocket.OPEN) return;
    const seq = S.seq;
    S.seq = (S.seq + 1) >>> 0;
    S.dirty = false;
    S.inFlight = seq;
    S.sentAt.set(seq, performance.now());
    ws.send(JSON.stringify({ seq, expression: expressionMessage(), camera: currentCamera() }));
  }

  // the request in flight may be lost with a reconnect or a server error: never wait forever
  setInterval(() => {
    if (S.inFlight !== null && performance.now() - (S.sentAt.get(S.inFlight) || 0) > 5000) {
      S.inFlight = null;
      if (S.dirty) sendNow();
    }
  }, 1000);

  // ------------------------------------------------------------------ stats
  setInterval(() => {
    const ft = S.frameTimes;
    const now = performance.now();
    const recent = ft.filter((t) => now - t <= 1000).length;
    // nothing to render: the picture is up to date, not "0 fps"
    const still = S.inFlight === null && !S.dirty;
    $("st-fps").textContent = !ft.length ? "–" : (recent === 0 && still ? "idle" : `${recent} fps`);
    $("st-fps").title = recent === 0 && still ? "the picture is up to date: nothing to render until something changes" : "frames drawn in the last second";
    const lat = [...S.latencies].sort((a, b) => a - b);
    $("st-lat").textContent = lat.length ? lat[Math.floor(lat.length / 2)].toFixed(0) : "–";
    $("st-render").textContent = S.lastRenderMs == null ? "–" : S.lastRenderMs.toFixed(1);
    $("st-dropped").textContent = `${S.serverDropped} · ${S.coalesced}`;
    $("st-frames").textContent = String(S.frames);
  }, 250);

  // ------------------------------------------------------------------ sequence player and auto-orbit
  function stopPlayer() {
    S.playing = false;
    clearInterval(S.playTimer);
    S.playTimer = null;
    $("play").textContent = "▶ play sequence";
  }
  $("play").addEventListener("click", () => {
    if (S.playing) { stopPlayer(); return; }
    if (!S.sequence || !S.model) return;
    const names = S.model.expression_names;
    S.playing = true;
    $("play").textContent = "❚❚ pause";
    const fps = Math.max(1, Math.min(60, Number($("play-fps").value) || 25));
    S.playTimer = setInterval(() => {
      const fr = S.sequence[S.playIndex % S.sequence.length];
      const vals = Array.isArray(fr) ? Object.fromEntries(names.map((n, i) => [n, Number(fr[i]) || 0])) : fr;
      setSliderValues(vals);
      $("play-pos").textContent = `${(S.playIndex % S.sequence.length) + 1}/${S.sequence.length}`;
      S.playIndex += 1;
      markDirty();
    }, 1000 / fps);
  });
  $("auto-orbit").addEventListener("change", (e) => {
    clearInterval(S.orbitTimer);
    S.orbitTimer = null;
    if (e.target.checked) S.orbitTimer = setInterval(() => { S.orbitPhase += 0.05; markDirty(); }, 40);
    markDirty();
  });

  // ------------------------------------------------------------------ camera: mouse and touch
  const canvas = $("frame");
  const pointers = new Map();
  let pinchDist = null;
  canvas.addEventListener("pointerdown", (e) => { canvas.setPointerCapture(e.pointerId); pointers.set(e.pointerId, [e.clientX, e.clientY]); });
  canvas.addEventListener("pointermove", (e) => {
    if (!pointers.has(e.pointerId)) return;
    const prev = pointers.get(e.pointerId);
    pointers.set(e.pointerId, [e.clientX, e.clientY]);
    if (pointers.size === 1) {
      S.cam.yaw = Math.max(-90, Math.min(90, S.cam.yaw - 0.4 * (e.clientX - prev[0])));
      S.cam.pitch = Math.max(-60, Math.min(60, S.cam.pitch + 0.4 * (e.clientY - prev[1])));
      markDirty();
    } else if (pointers.size === 2) {
      const [a, b] = [...pointers.values()];
      const d = Math.hypot(a[0] - b[0], a[1] - b[1]);
      if (pinchDist) zoom(pinchDist / d);
      pinchDist = d;
    }
  });
  const release = (e) => { pointers.delete(e.pointerId); if (pointers.size < 2) pinchDist = null; };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); zoom(Math.exp(e.deltaY * 0.001)); }, { passive: false });
  function zoom(factor) {
    S.cam.radius = Math.max(0.4, Math.min(3.0, S.cam.radius * factor));
    markDirty();
  }
  $("reset-cam").addEventListener("click", () => { S.cam = { ...CAM_DEFAULT }; markDirty(); });
  $("size").addEventListener("change", () => {
    S.size = Math.min((S.model && S.model.max_output_size) || 1024, Number($("size").value));
    markDirty();
  });

  window.addEventListener("beforeunload", () => closeStream());
  loadModel();
  loadSampleList();
})();

// What the server reports about an avatar's frames and photos (docs/protocol.md, GET /v1/avatars/{id}),
// as client_demo/client.py's describe_avatar: " · view blending on (4 views, tau 20°) · same person: ...".
function describeAvatar(av) {
  const parts = [];
  const vb = av.view_blend;
  if (vb) {
    if (vb.active) {  // views beyond the photos are mirrored views of turned photos (docs/protocol.md)
      const n = av.num_images, m = Number.isInteger(n) && vb.views > n ? vb.views - n : 0;
      parts.push(`view blending on (${vb.views} views${m ? `: ${n} photo${n === 1 ? "" : "s"} + ${m} mirrored` : ""}, tau ${vb.tau_deg}°)`);
    }
    else if (!vb.per_view_data) parts.push("view blending off (no per-view data: photos sent with cameras alone)");
    else if (vb.views < 2) parts.push("view blending off (one input view)");
    else parts.push("view blending off (the server's tau is 0)");
  }
  const sp = av.same_person;
  if (sp) {
    if (!sp.checked) parts.push(`same person: not checked (${sp.reason || "no reason given"})`);
    else if (sp.photos_compared < 2) parts.push("same person: fewer than two photos with a frontal face, nothing compared");
    else parts.push(`same person: ${sp.photos_compared} photos compared` + (sp.max_distance != null ? ` (largest distance ${sp.max_distance.toFixed(2)})` : ""));
  }
  return parts.map((p) => ` · ${p}`).join("");
}

