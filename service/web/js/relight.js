// Panel 4: relight the shown frame of a finished reconstruction under an uploaded environment
// map (rotated about the up axis) plus added lights: POST /v1/renders, then show the relit
// images (or the API's error, as it says it).

import { blobUrl, followJob, getJson, listAll, request, submitJson, waitText } from './api.js';
import { $, el, on, showError, showStatus } from './ui.js';

const state = { job: null, frame: null, index: 0, schema: null };
const ROTATION_NAMES = ['rotation_deg', 'envmap_rotation_deg', 'envmap_rotation', 'rotation'];

/** The properties of a request schema of the served OpenAPI document (what this server takes). */
async function renderSchema() {
  if (!state.schema) {
    const doc = await getJson('/openapi.json');
    const schemas = doc.components.schemas;
    state.schema = { render: schemas.RenderIn.properties, light: (schemas.LightIn || {}).properties || {} };
  }
  return state.schema;
}

async function loadEnvmaps(select) {
  const assets = await listAll('/v1/assets');
  const keep = select || $('envmap-select').value;
  $('envmap-select').replaceChildren(
    ...assets.filter((a) => a.kind === 'envmap').map((a) => el('option', {
      value: a.id, textContent: `${a.filename} (${a.width}x${a.height})` })),
    ...['studio', 'sunset', 'neon'].map((name) => el('option', {
      value: `builtin:${name}`, textContent: `built-in: ${name}` })),
    el('option', { value: '', textContent: 'none (black: lights only)' }));
  if ([...$('envmap-select').options].some((o) => o.value === keep)) $('envmap-select').value = keep;
}

async function uploadEnvmap() {
  const status = $('relight-status');
  const file = $('envmap-file').files[0];
  if (!file) return;
  const name = file.name.replace(/[^A-Za-z0-9_.-]/g, '_').replace(/^[^A-Za-z0-9]+/, '');
  showStatus(status, `uploading ${file.name}…`);
  try {
    const r = await request('POST', `/v1/assets?${new URLSearchParams({ filename: name, kind: 'envmap' })}`,
                            { body: file, headers: { 'Content-Type': 'application/octet-stream' } });
    const asset = await r.json();
    await loadEnvmaps(asset.id);
    showStatus(status, `environment map ${asset.filename} uploaded (${asset.width}x${asset.height})`, 'succeeded');
  } catch (err) {
    showError(status, err, 'environment map refused: ');
  } finally {
    $('envmap-file').value = '';
  }
}

function addLight() {
  const num = (value, cls, step = '0.1') => el('input', { type: 'number', value, step, className: cls });
  const row = el('div', { className: 'light' },
    el('label', {}, 'towards x', num('1', 'lx')), el('label', {}, 'y', num('1', 'ly')),
    el('label', {}, 'z', num('1', 'lz')),
    el('label', {}, 'colour', el('input', { type: 'color', value: '#ffffff', className: 'lc' })),
    el('label', {}, 'intensity', num('3', 'li', '0.5')),
    el('button', { type: 'button', className: 'secondary', textContent: 'remove', onclick: () => row.remove() }));
  $('lights').append(row);
}

function lights(lightSchema) {
  return [...$('lights').querySelectorAll('.light')].map((row) => {
    const v = (cls) => Number(row.querySelector(`.${cls}`).value);
    const hex = row.querySelector('.lc').value;
    const color = [1, 3, 5].map((i) => parseInt(hex.slice(i, i + 2), 16) / 255);
    const light = { direction: [v('lx'), v('ly'), v('lz')], color, intensity: v('li') };
    if ('kind' in lightSchema) light.kind = 'directional';
    return light;
  });
}

async function show(items) {
  // The videos (an orbit per frame) first, then at most a dozen pictures.
  const videos = items.filter((a) => a.content_type === 'video/mp4');
  const images = items.filter((a) => a.content_type === 'image/png').slice(0, videos.length ? 4 : 12);
  const path = (a) => new URL(a.url, location.href).pathname;
  const figs = await Promise.all([
    ...videos.map(async (a) => el('figure', {}, el('video', {
      src: await blobUrl(path(a)), controls: true, loop: true, autoplay: true, muted: true,
      className: 'relit' }), el('figcaption', { textContent: a.path }))),
    ...images.map(async (a) => el('figure', {}, el('img', {
      alt: a.path, src: await blobUrl(path(a)), className: 'relit' }),
    el('figcaption', { textContent: a.path })))]);
  $('relight-result').replaceChildren(...figs);
  return figs.length;
}

async function render() {
  const status = $('relight-status');
  if (!state.job || state.job.state !== 'succeeded') {
    showStatus(status, 'pick a succeeded reconstruction job first (panel 2)', 'error');
    return;
  }
  $('relight-render').disabled = true;
  showStatus(status, 'requesting the render…', 'busy');
  try {
    const schema = await renderSchema();
    const body = { job_id: state.job.id, lights: lights(schema.light), cameras: 'heldout',
                   frames: String(state.index) };
    if ($('envmap-select').value) body.envmap = $('envmap-select').value;
    const orbit = Number($('relight-orbit').value);
    if (orbit > 0) body.orbit = orbit;
    const rotation = ROTATION_NAMES.find((n) => n in schema.render);
    const degrees = Number($('envmap-rotation').value);
    if (rotation) body[rotation] = degrees;
    else if (degrees) showStatus(status, 'this server takes no environment rotation; rendering unrotated');
    const out = await submitJson('/v1/renders', body,
      { onWait: (left, err) => showStatus(status, waitText(left, err), 'waiting') });
    let items = out.items || out.artifacts || null;
    if (!items && out.id) {
      const job = await followJob(out.id, (event) => {
        const p = event.data;
        if (p.fraction != null) showStatus(status, `rendering: ${Math.round(100 * p.fraction)}% ${p.stage || ''}`);
      });
      if (job.state !== 'succeeded') {
        throw new Error(`the render job ${job.id} ${job.state}${job.error ? `: ${job.error.message}` : ''}`);
      }
      items = (await listAll(`/v1/jobs/${job.id}/artifacts`)).filter((a) => a.kind === 'relit' || a.path.startsWith('relit/'));
    }
    const n = await show(items || []);
    showStatus(status, n ? `relit: ${n} picture(s) or video(s)` : 'the render finished without images', n ? 'succeeded' : 'error');
  } catch (err) {
    showError(status, err, 'render failed: ');
  } finally {
    $('relight-render').disabled = false;
  }
}

export function initRelight() {
  $('envmap-file').addEventListener('change', uploadEnvmap);
  $('envmap-rotation').addEventListener('input', () => { $('rotation-label').textContent = `${$('envmap-rotation').value}°`; });
  $('light-add').addEventListener('click', addLight);
  $('relight-render').addEventListener('click', render);
  on('job', (job) => { state.job = job; });
  on('frame', ({ job, frame, index }) => { state.job = job; state.frame = frame; state.index = index; });
  loadEnvmaps().catch((err) => showError($('relight-status'), err));
}
