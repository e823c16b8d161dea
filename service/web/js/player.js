// Panel 5: the sequence played from its relightable stream (export/stream.dgss of an `export`
// job, POST /v1/exports, made on first use): the header and then each group of pictures fetched
// by HTTP ranges in the background, playing as soon as the first group is in; play, pause, scrub
// and loop at the capture's frame rate; orbit or a capture camera; relit live under the relight
// panel's environment map, rotation and lights (views: relit, appearance, normals, AO).

import { auth, followJob, getJson, listAll, submitJson, waitText } from './api.js';
import { DeferredSplats, upFrame } from './deferred.js';
import { GroupDecoder, StreamSource } from './stream.js';
import { $, el, on, showError, showStatus } from './ui.js';

/** Bytes [start, end) of `url` (a 200 answer, from a server without ranges, is sliced). */
export async function fetchRange(url, start, end) {
  const r = await fetch(url, { headers: auth.headers({ Range: `bytes=${start}-${end - 1}` }) });
  if (r.status === 416) return new Uint8Array(0);
  if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
  const bytes = new Uint8Array(await r.arrayBuffer());
  return r.status === 206 ? bytes : bytes.subarray(start, end);
}

const sub = (a, b) => a.map((v, i) => v - b[i]);
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const unit = (a) => { const l = Math.hypot(...a) || 1; return a.map((v) => v / l); };

/** An OpenCV world_to_camera looking from `eye` at `target` with `up` up the picture. */
export function lookAt(eye, target, up) {
  const f = unit(sub(target, eye)), r = unit(cross(f, up)), d = cross(f, r);
  const t = [r, d, f].map((row) => -(row[0] * eye[0] + row[1] * eye[1] + row[2] * eye[2]));
  return [[...r, t[0]], [...d, t[1]], [...f, t[2]], [0, 0, 0, 1]];
}

export class Player {
  constructor(canvas, status) {
    this.renderer = new DeferredSplats(canvas);
    this.canvas = canvas;
    this.status = status;
    this.index = 0;
    this.playing = false;
    this.loop = true;
    this.mode = 'relit';
    this.cameraId = 'orbit';
    this.orbit = { yaw: 0.6, pitch: 0.25, distance: 3, target: [0, 0, 0] };
    this.look = { env: Array.from({ length: 9 }, () => [0, 0, 0]), rotation: 0, lights: [] };
    this.stats = { decodeMs: [], drawMs: [], shown: 0, dropped: 0, fetched: 0 };
    this.error = null;
    this.attachOrbit();
  }

  /** Open the stream at `url`: the header now, the groups in the background, in order. */
  async open(url, fetcher = fetchRange) {
    this.stop();
    this.source = new StreamSource(url, fetcher);
    this.header = await this.source.open();
    this.decoder = null;
    this.error = null;
    this.index = 0;
    this.prefetch = (async () => {
      for (let g = 0; g < this.header.groups.length; g++) {
        await this.source.payload(g);
        this.stats.fetched = g + 1;
        this.onProgress?.();
      }
    })().catch((err) => this.fail(err));
    await this.source.payload(0);
    const first = this.decodeFrame(0);
    this.frameOrbit(first);
    this.draw();
    return this.header;
  }

  fail(err) {
    this.error = err;
    this.stop();
    showError(this.status, err, 'stream refused: ');
  }

  frameOrbit(frame) {
    const n = frame.count, m = frame.means, c = [0, 1, 2].map((k) => {
      const v = Float32Array.from({ length: n }, (_, i) => m[3 * i + k]).sort();
      return [v[Math.floor(0.02 * (n - 1))], v[Math.floor(0.5 * (n - 1))], v[Math.floor(0.98 * (n - 1))]];
    });
    this.orbit.target = c.map((x) => x[1]);
    this.orbit.distance = 1.4 * Math.max(1e-3, Math.hypot(...c.map((x) => x[2] - x[0])));
  }

  /** The decoded frame `k` (its group must have arrived); decoding runs forward in a group. */
  decodeFrame(k) {
    const [g, i] = this.source.frameGroup[k];
    const t0 = performance.now();
    if (!this.decoder || this.decoderGroup !== g || this.decoder.index > i) {
      this.decoder = new GroupDecoder(this.source.payloads.get(g));
      this.decoderGroup = g;
      this.current = null;
    }
    while (this.decoder.index < i) this.current = this.decoder.frame();
    this.stats.decodeMs.push(performance.now() - t0);
    this.renderer.setFrame(this.current);
    this.index = k;
    return this.current;
  }

  camera() {
    const cams = this.header.cameras || [];
    const fixed = cams.find((c) => c.id === this.cameraId);
    if (fixed) return fixed;
    const base = cams[0] || { width: 480, height: 360, K: [[450, 0, 240], [0, 450, 180], [0, 0, 1]] };
    const up = this.header.up || [0, 0, 1], o = this.orbit, [e1, e2] = upFrame(up);
    const dir = [0, 1, 2].map((k) => Math.cos(o.pitch) * (Math.cos(o.yaw) * e1[k] + Math.sin(o.yaw) * e2[k]) + Math.sin(o.pitch) * up[k]);
    const eye = o.target.map((v, k) => v + o.distance * dir[k]);
    // The orbit draws at least 480 pixels across, whatever the capture's resolution.
    const k = Math.max(1, 480 / Math.max(base.width, base.height));
    const K = [[base.K[0][0] * k, 0, base.K[0][2] * k], [0, base.K[1][1] * k, base.K[1][2] * k], [0, 0, 1]];
    return { width: Math.round(base.width * k), height: Math.round(base.height * k), K,
             world_to_camera: lookAt(eye, o.target, up) };
  }

  shading() {
    const h = this.header, rot = -this.look.rotation * Math.PI / 180;
    const F = upFrame(h.up || [0, 0, 1]), c = Math.cos(rot), s = Math.sin(rot);
    const frame = [F[0].map((v, k) => c * v - s * F[1][k]), F[0].map((v, k) => s * v + c * F[1][k]), F[2]];
    return { mode: this.mode, render: h.render, env: this.look.env, frame,
             capture: (h.capture_light && h.capture_light.uniform) || Math.PI, lights: this.look.lights };
  }

  draw() {
    if (!this.header || this.error) return;
    const t0 = performance.now();
    this.renderer.draw(this.camera(), this.shading());
    this.stats.drawMs.push(performance.now() - t0);
    this.stats.shown += 1;
    this.canvas.dataset.frame = String(this.index);
    this.onFrame?.(this.index);
  }

  requestDraw() {
    if (this.pending || this.playing) return;
    this.pending = requestAnimationFrame(() => { this.pending = 0; this.draw(); });
  }

  /** Show frame `k` now, if its group has arrived (else say what it waits for). */
  show(k) {
    const [g] = this.source.frameGroup[k];
    if (!this.source.has(g)) {
      showStatus(this.status, `buffering: group ${g + 1} of ${this.header.groups.length}…`, 'busy');
      this.source.payload(g).then(() => { if (!this.playing) this.show(k); }, (err) => this.fail(err));
      return false;
    }
    try {
      this.decodeFrame(k);
      this.draw();
    } catch (err) {
      this.fail(err);
      return false;
    }
    return true;
  }

  play() {
    if (!this.header || this.error) return;
    this.playing = true;
    const fps = this.header.fps, n = this.source.frames;
    if (this.index >= n - 1) this.show(0);  // played to the end: from the start again
    let start = null, last = this.index;
    const tick = (now) => {
      if (!this.playing) return;
      if (start === null) start = now - last * 1000 / fps;
      let k = Math.max(0, Math.floor((now - start) * fps / 1000));
      if (k >= n) {
        if (!this.loop) {  // the last frame stays on screen, also when it was due but dropped
          if (last !== n - 1) this.show(n - 1);
          this.stop();
          this.onEnd?.();
          return;
        }
        start = now;
        k = 0;
      }
      if (k !== last) {
        const [g] = this.source.frameGroup[k];
        if (!this.source.has(g)) { start = now - last * 1000 / fps; showStatus(this.status, `buffering group ${g + 1}…`, 'busy'); } else {
          this.stats.dropped += Math.max(0, k - last - 1);
          if (this.show(k)) last = k;
        }
      }
      this.timer = requestAnimationFrame(tick);
    };
    this.timer = requestAnimationFrame(tick);
  }

  stop() {
    this.playing = false;
    if (this.timer) cancelAnimationFrame(this.timer);
    this.timer = 0;
  }

  attachOrbit() {
    const c = this.canvas, o = this.orbit;
    let drag = null;
    c.addEventListener('pointerdown', (e) => { drag = [e.clientX, e.clientY]; c.setPointerCapture(e.pointerId); });
    c.addEventListener('pointerup', () => { drag = null; });
    c.addEventListener('pointermove', (e) => {
      if (!drag || this.cameraId !== 'orbit') return;
      o.yaw -= (e.clientX - drag[0]) * 0.01;
      o.pitch = Math.max(-1.5, Math.min(1.5, o.pitch + (e.clientY - drag[1]) * 0.01));
      drag = [e.clientX, e.clientY];
      this.requestDraw();
    });
    c.addEventListener('wheel', (e) => { e.preventDefault(); o.distance *= Math.exp(e.deltaY * 0.001); this.requestDraw(); }, { passive: false });
  }
}

// -- the panel -------------------------------------------------------------------------------
const state = { job: null, player: null, sh9: new Map() };

async function envmapSh9(value) {
  if (!value) return Array.from({ length: 9 }, () => [0, 0, 0]);
  if (value.startsWith('builtin:')) return state.player.header.envmaps[value];
  if (!state.sh9.has(value)) state.sh9.set(value, (await getJson(`/v1/assets/${value}`)).sh9);
  const sh9 = state.sh9.get(value);
  if (!sh9) throw new Error('this environment map was stored before maps carried their SH9; upload it again');
  return sh9;
}

function panelLights() {
  return [...$('lights').querySelectorAll('.light')].map((row) => {
    const v = (cls) => Number(row.querySelector(`.${cls}`).value);
    const hex = row.querySelector('.lc').value;
    return { kind: 'directional', vector: [v('lx'), v('ly'), v('lz')], intensity: v('li'),
             color: [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255) };
  });
}

async function relook() {
  const p = state.player;
  if (!p || !p.header) return;
  try {
    p.look = { env: await envmapSh9($('envmap-select').value), rotation: Number($('envmap-rotation').value),
               lights: panelLights() };
    p.requestDraw();
  } catch (err) {
    showError($('player-status'), err, 'relight: ');
  }
}

/** The succeeded export job with a stream of reconstruction `job` (of its subject alone when
 * `subject`: the Gaussians inside the masks' hull), made when there is none. */
async function streamJob(job, status, subject = false) {
  const jobs = await listAll('/v1/jobs', { state: 'succeeded' });
  const done = jobs.find((j) => j.source_job_id === job.id && j.pipeline === 'export'
    && (j.params.formats || ['stream']).includes('stream') && Boolean(j.params.subject) === subject);
  if (done) return done;
  showStatus(status, `making the ${subject ? "subject's " : ''}stream (an export job)…`, 'busy');
  const queued = await submitJson('/v1/exports', { job_id: job.id, formats: ['stream'], subject },
    { onWait: (left, err) => showStatus(status, waitText(left, err), 'waiting') });
  const out = await followJob(queued.id, (e) => {
    if (e.data.fraction != null) showStatus(status, `exporting: ${Math.round(100 * e.data.fraction)}%`, 'busy');
  });
  if (out.state !== 'succeeded') throw new Error(`the export job ${out.id} ${out.state}${out.error ? `: ${out.error.message}` : ''}`);
  return out;
}

/** Open a stream by URL (also what tests and the benchmark call). */
export async function openStream(url) {
  const status = $('player-status');
  if (!state.player) state.player = new Player($('player-canvas'), status);
  const p = state.player;
  showStatus(status, 'opening the stream…', 'busy');
  const header = await p.open(url);
  const cams = header.cameras || [];
  $('player-camera').replaceChildren(el('option', { value: 'orbit', textContent: 'orbit (drag)' }),
    ...cams.map((c) => el('option', { value: c.id, textContent: `${c.id}${c.heldout ? ' (held out)' : ''}` })));
  $('player-scrub').max = String(p.source.frames - 1);
  $('player-scrub').value = '0';
  $('player-play').disabled = false;
  p.onFrame = (k) => { $('player-scrub').value = String(k); $('player-frame').textContent = `${header.frames[k]} (${k + 1}/${p.source.frames})`; };
  p.onProgress = () => showStatus(status, `${p.source.frames} frames at ${header.fps} fps; ${p.stats.fetched} of ${header.groups.length} groups loaded`, p.stats.fetched === header.groups.length ? 'succeeded' : 'busy');
  p.onEnd = () => { $('player-play').textContent = 'Play'; };
  p.onProgress();
  await relook();
  return p;
}

async function openFor(job) {
  const status = $('player-status');
  const id = $('job-select').value || (job && job.id);
  if (id) job = await getJson(`/v1/jobs/${id}`).catch(() => job);
  if (!job || job.state !== 'succeeded' || job.pipeline !== 'reconstruct') {
    showStatus(status, 'pick a succeeded reconstruction (panel 2) first', 'error');
    return;
  }
  try {
    const exp = await streamJob(job, status, $('player-subject').checked);
    await openStream(`/v1/jobs/${exp.id}/artifacts/export/stream.dgss`);
  } catch (err) {
    showError(status, err, 'player: ');
  }
}

export function initPlayer() {
  window.dgsPlayer = { open: openStream, get player() { return state.player; } };
  on('job', (job) => { state.job = job; });
  $('player-open').addEventListener('click', () => openFor(state.job));
  $('player-play').addEventListener('click', () => {
    const p = state.player;
    if (!p) return;
    if (p.playing) { p.stop(); $('player-play').textContent = 'Play'; } else { p.play(); $('player-play').textContent = 'Pause'; }
  });
  $('player-scrub').addEventListener('input', () => state.player && state.player.show(Number($('player-scrub').value)));
  $('player-loop').addEventListener('change', () => { if (state.player) state.player.loop = $('player-loop').checked; });
  $('player-view').addEventListener('change', () => { if (state.player) { state.player.mode = $('player-view').value; state.player.requestDraw(); } });
  $('player-camera').addEventListener('change', () => { if (state.player) { state.player.cameraId = $('player-camera').value; state.player.requestDraw(); } });
  for (const id of ['envmap-select', 'envmap-rotation']) $(id).addEventListener('input', relook);
  $('envmap-select').addEventListener('change', relook);
  $('lights').addEventListener('input', relook);
  new MutationObserver(relook).observe($('lights'), { childList: true });
}
