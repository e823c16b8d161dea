// Panel 1: a capture folder goes up as a manifest (path, size, SHA-256 per file), then one tus
// upload per file the server is missing, then a commit (validate and freeze).

import { formatBytes, getJson, listAll, request, sendJson } from './api.js';
import { sha256File } from './sha256.js';
import { TusUpload, terminate } from './tus.js';
import { $, el, emit, on, showError, showStatus } from './ui.js';

const CANONICAL = /^(capture\.json$|points\.ply$|images\/|masks\/|normals\/)/;
const state = { files: new Map(), captureId: null, upload: null, paused: false, busy: false };

/** path -> File for the picked folder: relative to its top folder, hidden files left out. */
function pickedFiles(fileList, format) {
  const files = new Map();
  let skipped = 0;
  for (const f of fileList) {
    const parts = (f.webkitRelativePath || f.name).split('/');
    const rel = parts.length > 1 ? parts.slice(1).join('/') : parts[0];
    if (rel.split('/').some((p) => p.startsWith('.')) || (format === 'canonical' && !CANONICAL.test(rel))) {
      skipped++;
      continue;
    }
    files.set(rel, f);
  }
  return { files, skipped };
}

function refreshPicked() {
  const input = $('capture-folder');
  const { files, skipped } = pickedFiles(input.files, $('capture-format').value);
  state.files = files;
  const first = input.files[0];
  if (first && !$('capture-name').value) {
    $('capture-name').value = (first.webkitRelativePath || '').split('/')[0] || 'capture';
  }
  const bytes = [...files.values()].reduce((n, f) => n + f.size, 0);
  $('upload-start').disabled = files.size === 0 || state.busy;
  showStatus($('upload-status'), files.size
    ? `${files.size} files, ${formatBytes(bytes)}${skipped ? ` (${skipped} left out)` : ''}` : '');
}

async function loadCaptures() {
  const select = $('capture-select');
  const keep = select.value;
  const captures = await listAll('/v1/captures', { state: 'uploading' });
  select.replaceChildren(el('option', { value: '', textContent: 'new, from a folder' }),
    ...captures.map((c) => el('option', { value: c.id,
      textContent: `resume ${c.name || c.id} (${formatBytes(c.total_bytes)})` })));
  if ([...select.options].some((o) => o.value === keep)) select.value = keep;
}

async function manifest(progress) {
  const entries = [];
  const total = [...state.files.values()].reduce((n, f) => n + f.size, 0);
  let done = 0;
  for (const [path, file] of state.files) {
    const sha256 = await sha256File(file, (n) => progress(done + n, total));
    done += file.size;
    entries.push({ path, size: file.size, sha256 });
  }
  return entries;
}

function setBusy(busy) {
  state.busy = busy;
  $('upload-start').disabled = busy || state.files.size === 0;
  $('upload-pause').hidden = !busy;
  $('upload-cancel').hidden = !busy && !state.paused;
}

async function commit(id) {
  const status = $('upload-status');
  showStatus(status, 'validating the capture…');
  let r = await request('POST', `/v1/captures/${id}/commit`);
  let capture = await r.json();
  while (capture.state === 'committing') {
    await new Promise((resolve) => setTimeout(resolve, 1000));
    capture = await getJson(`/v1/captures/${id}`);
  }
  if (capture.state !== 'ready') {
    throw new Error(capture.error ? capture.error.message : `capture ${id} is ${capture.state}`);
  }
  const s = capture.summary;
  showStatus(status, `capture ${id} is ready: ${s.frames} frame(s), ${s.cameras} cameras, ` +
                     `${s.views} views`, 'succeeded');
  return capture;
}

async function upload() {
  const status = $('upload-status'), bar = $('upload-progress');
  setBusy(true);
  state.paused = false;
  try {
    if (!state.captureId) {
      const chosen = $('capture-select').value;
      if (chosen) {
        state.captureId = chosen;
      } else {
        const files = await manifest((n, total) => {
          bar.value = total ? n / total : 1;
          showStatus(status, `hashing: ${formatBytes(n)} of ${formatBytes(total)}`);
        });
        const capture = await sendJson('POST', '/v1/captures', {
          name: $('capture-name').value, format: $('capture-format').value, manifest: { files } });
        state.captureId = capture.id;
        emit('captures');
      }
    }
    const id = state.captureId;
    const missing = await listAll(`/v1/captures/${id}/files`, { state: 'missing' });
    const absent = missing.filter((f) => !state.files.has(f.path));
    if (absent.length) {
      throw new Error(`the picked folder lacks ${absent.length} file(s) of capture ${id}, e.g. ${absent[0].path}`);
    }
    const total = missing.reduce((n, f) => n + f.size, 0);
    let done = 0;
    for (const [i, f] of missing.entries()) {
      const before = done;
      state.upload = new TusUpload(state.files.get(f.path), {
        captureId: id, path: f.path,
        onProgress: (n) => {
          bar.value = total ? (before + n) / total : 1;
          showStatus(status, `uploading ${i + 1}/${missing.length} ${f.path}: ` +
                             `${formatBytes(before + n)} of ${formatBytes(total)}`);
        },
      });
      await state.upload.start();
      done += f.size;
    }
    state.upload = null;
    bar.value = 1;
    await commit(id);
    state.captureId = null;
    emit('captures');
    emit('capture-ready', id);
  } catch (err) {
    if (err.code === 'aborted') {
      showStatus(status, `paused: ${status.textContent}`);
      state.paused = true;
    } else {
      showError(status, err, 'upload failed: ');
    }
  } finally {
    setBusy(false);
    $('upload-start').textContent = state.paused ? 'Resume' : 'Upload';
  }
}

async function cancel() {
  const id = state.captureId;
  if (state.upload) {
    state.upload.abort();
    const url = localStorage.getItem(state.upload.storeKey);
    if (url) await terminate(url).catch(() => {});
    localStorage.removeItem(state.upload.storeKey);
  }
  state.upload = null;
  state.captureId = null;
  state.paused = false;
  if (id) {
    try {
      await request('DELETE', `/v1/captures/${id}`);
      showStatus($('upload-status'), `capture ${id} deleted`);
    } catch (err) {
      showError($('upload-status'), err, 'cancel: ');
    }
  }
  $('upload-progress').value = 0;
  $('upload-start').textContent = 'Upload';
  setBusy(false);
  emit('captures');
}

export function initCapture(info) {
  // The source formats come from the server's importers (GET /v1/info), never a list here.
  $('capture-format').append(...Object.entries(info.capture_formats || {}).map(
    ([name, what]) => el('option', { value: name, textContent: name, title: what })));
  $('capture-folder').addEventListener('change', refreshPicked);
  $('capture-format').addEventListener('change', refreshPicked);
  $('capture-select').addEventListener('change', () => {
    state.captureId = null;
    $('upload-start').textContent = $('capture-select').value ? 'Resume upload' : 'Upload';
  });
  $('upload-start').addEventListener('click', upload);
  $('upload-pause').addEventListener('click', () => { if (state.upload) state.upload.abort(); });
  $('upload-cancel').addEventListener('click', cancel);
  on('captures', () => loadCaptures().catch((err) => showError($('upload-status'), err)));
}
