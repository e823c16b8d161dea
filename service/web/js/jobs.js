// Panel 2: start a reconstruction on a ready capture with a preset, and follow a job live
// (server-sent events, read with fetch so the key stays in a header), with its log.

import { followJob, getJson, listAll, sendJson, submitJson, waitText } from './api.js';
import { $, el, emit, on, showError, showStatus } from './ui.js';

const TERMINAL = new Set(['succeeded', 'failed', 'cancelled']);
const state = { watching: null, job: null, logOffset: 0, logTimer: 0 };

function describe(job) {
  const p = job.progress || job;
  const parts = [`job ${job.id || state.job.id}: ${job.state}`];
  if (p.stage) parts.push(`stage ${p.stage}`);
  if (p.frames) parts.push(`frame ${Math.min(p.frame + 1, p.frames)}/${p.frames}`);
  if (p.iterations) parts.push(`step ${p.iteration}/${p.iterations}`);
  if (p.fraction != null) parts.push(`${Math.round(100 * p.fraction)}%`);
  if (p.eta_s != null && !TERMINAL.has(job.state)) parts.push(`about ${Math.ceil(p.eta_s)} s left`);
  if (job.error) parts.push(`error: ${job.error.message}`);
  return parts.join(' · ');
}

// A sequence run as parts (one per group of pictures): a strip with a cell per part, queued,
// running with its percentage, done or failed; its tooltip names the worker that runs or ran
// it and every earlier run (a lost or released one included), so a bad node can be found.
const CELL = { queued: '', running: null, succeeded: '✓', failed: '✗', cancelled: '–' };

function partTitle(part, pct) {
  const frames = part.frames || [];
  let title = `part ${part.index}: frames ${frames[0]}..${frames[frames.length - 1]}, ${part.state}`;
  if (part.state === 'running') title += ` ${pct}%`;
  if (part.worker) title += ` on ${part.worker}`;
  const runs = part.runs || [];
  if (runs.length > 1 || (runs.length === 1 && runs[0].worker !== part.worker)) {
    title += '\nruns: ' + runs.map((r) => `${r.worker} (${r.outcome || 'running'})`).join(', ');
  }
  return title;
}

function renderParts(parts) {
  const strip = $('job-parts');
  strip.hidden = !parts || parts.length === 0;
  if (strip.hidden) return;
  strip.replaceChildren(...parts.map((part) => {
    const pct = Math.round(100 * (part.fraction || 0));
    const cell = el('span', {
      className: `part part-${part.state}`,
      textContent: CELL[part.state] ?? `${pct}%`,
      title: partTitle(part, pct),
    });
    if (part.worker) cell.dataset.worker = part.worker;
    if (part.state === 'running') {
      cell.style.background = `linear-gradient(to right, var(--part-done) ${pct}%, var(--part-left) ${pct}%)`;
    }
    return cell;
  }));
}

function updatePart(job, data) {
  const parts = (job.parts || []).map((part) => (part.index === data.part
    ? { ...part, ...data, index: part.index, state: data.event === 'progress' ? 'running' : (data.state || part.state) }
    : part));
  return { ...job, parts };
}

function render(job) {
  const p = job.progress || job;
  if (p.fraction != null) $('job-progress').value = p.fraction;
  renderParts(job.parts);
  showStatus($('job-status'), describe(job), job.state);
  $('job-cancel').hidden = TERMINAL.has(job.state);
  $('job-retry').hidden = !['failed', 'cancelled'].includes(job.state);
}

async function pollLog() {
  const job = state.job;
  if (!job) return;
  try {
    const page = await getJson(`/v1/jobs/${job.id}/logs?offset=${state.logOffset}`);
    if (state.job !== job) return;
    if (page.lines.length) {
      const pre = $('job-log');
      pre.textContent += page.lines.join('\n') + '\n';
      const lines = pre.textContent.split('\n');
      if (lines.length > 500) pre.textContent = lines.slice(-500).join('\n');
      pre.scrollTop = pre.scrollHeight;
    }
    state.logOffset = page.next_offset;
    if (!page.complete) state.logTimer = setTimeout(pollLog, 2000);
  } catch {
    state.logTimer = setTimeout(pollLog, 5000);
  }
}

async function watch(jobId) {
  if (state.watching) state.watching.abort();
  clearTimeout(state.logTimer);
  const ctl = new AbortController();
  state.watching = ctl;
  $('job-log').textContent = '';
  state.logOffset = 0;
  try {
    let job = await getJson(`/v1/jobs/${jobId}`);
    state.job = job;
    render(job);
    emit('job', job);
    pollLog();
    let frame = job.progress.frame;
    job = await followJob(jobId, (event) => {
      if (ctl.signal.aborted) return;
      if (event.kind === 'part') { // one part changed: its cell, not the job's progress
        state.job = updatePart(state.job, event.data);
        renderParts(state.job.parts);
        return;
      }
      const data = { ...state.job, ...event.data, progress: { ...state.job.progress, ...event.data } };
      state.job = data;
      render(data);
      if (data.progress.frame !== frame) {
        frame = data.progress.frame;
        emit('job', data); // a finished frame's artifacts are published as it completes
      }
    }, ctl.signal);
    if (ctl.signal.aborted) return;
    state.job = job;
    render(job);
    emit('job', job);
    await loadJobs();
  } catch (err) {
    if (!ctl.signal.aborted) showError($('job-status'), err);
  }
}

async function loadJobs() {
  const page = await getJson('/v1/jobs?limit=50');
  const select = $('job-select');
  const keep = state.job ? state.job.id : select.value;
  select.replaceChildren(el('option', { value: '', textContent: '—' }),
    ...page.items.filter((j) => j.pipeline === 'reconstruct').map((j) => el('option', {
      value: j.id, textContent: `${j.id} ${j.name} (${j.state})` })));
  if ([...select.options].some((o) => o.value === keep)) select.value = keep;
}

async function loadReadyCaptures() {
  const captures = await listAll('/v1/captures', { state: 'ready' });
  const select = $('job-capture');
  const keep = select.value;
  select.replaceChildren(...captures.map((c) => el('option', {
    value: c.id, textContent: `${c.name || c.id} (${c.summary ? `${c.summary.frames} frames, ${c.summary.cameras} cameras` : c.id})` })));
  if ([...select.options].some((o) => o.value === keep)) select.value = keep;
  $('job-start').disabled = captures.length === 0;
}

async function start() {
  const status = $('job-status');
  let config;
  try {
    config = JSON.parse($('job-config').value || '{}');
  } catch (err) {
    showError(status, `configuration overrides: not JSON (${err.message})`);
    return;
  }
  // The select sets the split unless the JSON overrides name one themselves.
  if (config.split === undefined && $('job-split').value !== 'auto') config.split = $('job-split').value;
  const params = { preset: $('job-preset').value, config };
  const frames = $('job-frames').value.trim();
  if (frames) params.frames = frames;
  $('job-start').disabled = true;
  try {
    const job = await submitJson('/v1/jobs', { capture_id: $('job-capture').value,
      pipeline: 'reconstruct', params, name: $('job-capture').selectedOptions[0].textContent.split(' (')[0] },
    { onWait: (left, err) => showStatus(status, waitText(left, err), 'waiting') });
    state.job = job;
    await loadJobs();
    watch(job.id);
  } catch (err) {
    showError(status, err, 'the job was refused: ');
  } finally {
    $('job-start').disabled = false;
  }
}

async function act(action) {
  try {
    await sendJson('POST', `/v1/jobs/${state.job.id}/${action}`, undefined,
      { onWait: (left, err) => showStatus($('job-status'), waitText(left, err), 'waiting') });
    if (action === 'retry') watch(state.job.id);
  } catch (err) {
    showError($('job-status'), err, `${action}: `);
  }
}

export async function initJobs() {
  const pipelines = await getJson('/v1/pipelines');
  const reconstruct = pipelines.find((p) => p.name === 'reconstruct');
  const preset = reconstruct.params_schema.properties.preset;
  $('job-preset').replaceChildren(...preset.enum.map((name) => el('option', { value: name, textContent: name })));
  $('job-preset').value = preset.default || preset.enum[0];
  $('job-preset').title = preset.description || '';
  $('job-start').addEventListener('click', start);
  $('job-select').addEventListener('change', () => { if ($('job-select').value) watch($('job-select').value); });
  $('job-cancel').addEventListener('click', () => act('cancel'));
  $('job-retry').addEventListener('click', () => act('retry'));
  on('captures', () => loadReadyCaptures().catch((err) => showError($('job-status'), err)));
  on('capture-ready', async (id) => { await loadReadyCaptures(); $('job-capture').value = id; });
  await loadJobs();
}
