// Panel 3: a job's artifacts: held-out renders with their normal, depth, AO and relit maps per
// frame (a scrubber over the frames of a sequence), training plots and the contact sheet,
// metrics, every file, and the splat viewer of a frame's PLY.

import { arrayBuffer, blobUrl, formatBytes, listAll } from './api.js';
import { SplatViewer, parsePly } from './splat.js';
import { $, el, emit, on, showError, showStatus } from './ui.js';

const MAPS = [['render', '_rgb.png', 'render'], ['normal', '_normal.png', 'normals'],
              ['depth', '_depth.npy', 'depth'], ['ao', '_ao.png', 'ambient occlusion'],
              ['relit', '_relit.png', 'relit (second light)']];
const state = { job: null, artifacts: [], frames: [], cameras: [], viewer: null, timer: 0,
                shown: '' };

const url = (a) => `/v1/jobs/${state.job.id}/artifacts/${a.path.split('/').map(encodeURIComponent).join('/')}`;

/** A .npy float array (docs/design.md 3.3 depth) as {shape, data}. */
export function parseNpy(buffer) {
  const bytes = new Uint8Array(buffer);
  if (bytes[0] !== 0x93 || String.fromCharCode(...bytes.subarray(1, 6)) !== 'NUMPY') throw new Error('not a .npy file');
  const major = bytes[6];
  const view = new DataView(buffer);
  const hlen = major === 1 ? view.getUint16(8, true) : view.getUint32(8, true);
  const start = major === 1 ? 10 : 12;
  const header = new TextDecoder('latin1').decode(bytes.subarray(start, start + hlen));
  const descr = /'descr':\s*'([^']+)'/.exec(header)[1];
  const shape = /'shape':\s*\(([^)]*)\)/.exec(header)[1].split(',').filter((s) => s.trim()).map(Number);
  if (/'fortran_order':\s*True/.test(header)) throw new Error('Fortran-ordered .npy is not supported');
  const off = start + hlen;
  const n = shape.reduce((a, b) => a * b, 1);
  let data;
  if (descr === '<f4') data = new Float32Array(buffer.slice(off, off + 4 * n));
  else if (descr === '<f8') data = Float32Array.from(new Float64Array(buffer.slice(off, off + 8 * n)));
  else throw new Error(`unsupported .npy dtype ${descr}`);
  return { shape, data };
}

/** A depth map drawn near-bright, far-dark, background (0 or non-finite) black. */
async function depthCanvas(a) {
  const { shape, data } = parseNpy(await arrayBuffer(url(a)));
  const [h, w] = shape;
  let lo = Infinity, hi = -Infinity;
  for (const v of data) if (Number.isFinite(v) && v > 0) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  const canvas = el('canvas', { width: w, height: h, className: 'depth' });
  const ctx = canvas.getContext('2d');
  const img = ctx.createImageData(w, h);
  for (let i = 0; i < w * h; i++) {
    const v = data[i * (data.length / (w * h))];
    const valid = Number.isFinite(v) && v > 0;
    const t = valid ? 1 - (v - lo) / Math.max(hi - lo, 1e-9) : 0;
    img.data.set(valid ? [255 * t ** 0.8, 255 * t, 255 * Math.min(1, 0.3 + t), 255] : [0, 0, 0, 255], 4 * i);
  }
  ctx.putImageData(img, 0, 0);
  const out = el('img', { alt: a.path });
  out.src = canvas.toDataURL();
  return out;
}

async function figure(a, caption) {
  const img = a.path.endsWith('.npy') ? await depthCanvas(a) : el('img', { alt: a.path, src: await blobUrl(url(a)) });
  img.dataset.path = a.path;
  return el('figure', {}, img, el('figcaption', { textContent: caption }));
}

function frameOf(i) { return state.frames[Math.max(0, Math.min(i, state.frames.length - 1))]; }

async function showFrame() {
  const frame = frameOf(Number($('frame-scrubber').value));
  $('frame-label').textContent = frame ? `${frame} (${Number($('frame-scrubber').value) + 1}/${state.frames.length})` : '';
  emit('frame', { job: state.job, frame, index: Number($('frame-scrubber').value) });
  const camera = $('camera-select').value;
  const cams = camera ? [camera] : state.cameras;
  const key = `${state.job.id}/${frame}/${cams.join(',')}/${state.artifacts.length}`;
  if (key === state.shown) return;
  state.shown = key;
  const figures = [];
  for (const cam of cams) {
    for (const [kind, suffix, label] of MAPS) {
      const a = state.artifacts.find((x) => x.kind === kind && x.path === `renders/${frame}/${cam}${suffix}`);
      if (a) figures.push(figure(a, `${cam} ${label}`));
    }
  }
  const done = await Promise.allSettled(figures);
  if (state.shown !== key) return;
  $('maps').replaceChildren(...done.filter((r) => r.status === 'fulfilled').map((r) => r.value));
}

async function showPlots() {
  // Training plots, and the run's pictures (the contact sheet of dgs eval).
  const plots = state.artifacts.filter((a) => a.kind === 'plot' || a.kind === 'image');
  const figs = await Promise.allSettled(plots.map(async (a) => {
    const fig = await figure(a, a.path.split('/').pop());
    if (a.kind === 'image') fig.className = 'wide';  // the contact sheet: a row of its own
    return fig;
  }));
  $('plots').replaceChildren(...figs.filter((r) => r.status === 'fulfilled').map((r) => r.value));
}

async function showMetrics() {
  const table = $('metrics');
  const evalFile = state.artifacts.find((a) => a.kind === 'eval');
  if (!evalFile) { table.replaceChildren(); return; }
  const data = JSON.parse(new TextDecoder().decode(await arrayBuffer(url(evalFile))));
  // What the metrics are on: held-out views, or training views for a run that held none out.
  const on = data.split ? data.split.scored_on : 'held-out views';
  $('metrics-on').textContent = `on ${on}${data.split && data.split.heldout.length ? ` (${data.split.heldout.join(', ')})` : ''}`;
  $('camera-select').options[0].textContent = `all ${on.replace(' views', '')}`;
  // Numbers at the top level, and one level down (relight.psnr, mesh.chamfer_relative, ...).
  const rows = Object.entries(data).flatMap(([k, v]) => (v !== null && typeof v === 'object' && !Array.isArray(v)
    ? Object.entries(v).map(([k2, v2]) => [`${k}.${k2}`, v2]) : [[k, v]]))
    .filter(([, v]) => v === null || typeof v === 'number');
  const show = (v) => (v === null ? '—' : Number.isInteger(v) ? String(v) : v.toFixed(4));
  table.replaceChildren(...rows.map(([k, v]) => el('tr', {},
    el('th', { textContent: k }), el('td', { textContent: show(v) }))));
}

async function download(a) {
  const link = el('a', { href: await blobUrl(url(a)), download: a.path.split('/').pop() });
  document.body.append(link);
  link.click();
  link.remove();
}

function showFiles() {
  $('files').replaceChildren(el('tr', {}, ...['path', 'kind', 'size', ''].map((t) => el('th', { textContent: t }))),
    ...state.artifacts.map((a) => el('tr', {}, el('td', { textContent: a.path }), el('td', { textContent: a.kind }),
      el('td', { textContent: formatBytes(a.size) }),
      el('td', {}, el('button', { type: 'button', className: 'secondary', textContent: 'download',
                                  onclick: () => download(a) })))));
}

async function load(job) {
  const fresh = !state.job || state.job.id !== job.id;
  state.job = job;
  const artifacts = await listAll(`/v1/jobs/${job.id}/artifacts`);
  if (state.job !== job) return;
  state.artifacts = artifacts;
  state.frames = [...new Set(artifacts.filter((a) => a.frame != null).map((a) => a.frame))].sort();
  state.cameras = [...new Set(artifacts.filter((a) => a.kind === 'render').map((a) => a.path.split('/').pop().replace(/_rgb\.png$/, '')))].sort();
  $('results-empty').hidden = state.frames.length > 0;
  $('results-body').hidden = state.frames.length === 0;
  const scrub = $('frame-scrubber');
  scrub.max = String(Math.max(0, state.frames.length - 1));
  if (fresh) scrub.value = '0';
  const cam = $('camera-select').value;
  $('camera-select').replaceChildren(el('option', { value: '', textContent: 'all held-out' }),
    ...state.cameras.map((c) => el('option', { value: c, textContent: c })));
  if (state.cameras.includes(cam)) $('camera-select').value = cam;
  if (fresh) showStatus($('viewer-status'), '');
  showFiles();
  await Promise.all([showFrame(), showPlots(), showMetrics()]);
  $('results').dataset.loaded = job.id;
}

async function viewFrame() {
  const status = $('viewer-status');
  const frame = frameOf(Number($('frame-scrubber').value));
  const ply = state.artifacts.find((a) => a.kind === 'ply' && a.frame === frame);
  if (!ply) { showStatus(status, `frame ${frame} has no Gaussians (yet)`); return; }
  try {
    if (!state.viewer) state.viewer = new SplatViewer($('viewer'));
    state.viewer.setUp($('viewer-up').value);
    state.viewer.mode = $('viewer-mode').value;
    showStatus(status, `loading ${ply.path} (${formatBytes(ply.size)})…`);
    const parsed = parsePly(await arrayBuffer(url(ply)));
    state.viewer.setGaussians(parsed);
    showStatus(status, `frame ${frame}: ${parsed.count} Gaussians`, 'succeeded');
    $('viewer').dataset.frame = frame;
  } catch (err) {
    showError(status, err, 'viewer: ');
  }
}

export function initResults() {
  on('job', (job) => load(job).catch((err) => showError($('job-status'), err, 'results: ')));
  $('frame-scrubber').addEventListener('input', () => showFrame());
  $('camera-select').addEventListener('change', () => showFrame());
  $('frame-play').addEventListener('click', () => {
    if (state.timer) {
      clearInterval(state.timer);
      state.timer = 0;
      $('frame-play').textContent = 'Play';
      return;
    }
    $('frame-play').textContent = 'Pause';
    state.timer = setInterval(() => {
      const s = $('frame-scrubber');
      s.value = String((Number(s.value) + 1) % (Number(s.max) + 1));
      showFrame();
    }, 400);
  });
  $('viewer-load').addEventListener('click', viewFrame);
  $('viewer-mode').addEventListener('change', () => state.viewer && state.viewer.setMode($('viewer-mode').value));
  $('viewer-up').addEventListener('change', () => state.viewer && state.viewer.setUp($('viewer-up').value));
}
