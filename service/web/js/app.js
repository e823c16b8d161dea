// The page: sign in, then the five panels (capture, job, results, relight, player). Panels talk through
// `bus` events: 'captures' (the list changed), 'capture-ready' (id), 'job' (a job object),
// 'frame' ({job, frame}).

import { auth, getJson } from './api.js';
import { initCapture } from './capture.js';
import { initJobs } from './jobs.js';
import { initPlayer } from './player.js';
import { initRelight } from './relight.js';
import { initResults } from './results.js';
import { $, emit } from './ui.js';

let started = false;

async function enter(info) {
  $('signin').hidden = true;
  $('workspace').hidden = false;
  $('whoami').textContent = `tenant ${info.tenant} · dgs ${info.version}`;
  $('signout').hidden = !auth.key;
  if (started) return;
  started = true;
  initCapture(info);
  await initJobs(info);
  initResults();
  initRelight();
  initPlayer();
  emit('captures');
}

async function trySignIn() {
  const info = await getJson('/v1/info');
  await enter(info);
}

function showSignIn(error) {
  $('boot').hidden = true;
  $('workspace').hidden = true;
  $('signin').hidden = false;
  $('signin-error').textContent = error ? (error.detail || String(error)) : '';
  $('api-key').focus();
}

async function boot() {
  $('signin-form').addEventListener('submit', async (e) => {
    e.preventDefault();
    const key = $('api-key').value.trim();
    if (!key) return;
    auth.set(key, $('remember').checked);
    try {
      await trySignIn();
      $('api-key').value = '';
    } catch (err) {
      auth.clear();
      showSignIn(err);
    }
  });
  $('signin-local').addEventListener('click', async () => {
    auth.clear();
    try { await trySignIn(); } catch (err) { showSignIn(err); }
  });
  $('signout').addEventListener('click', () => { auth.clear(); location.reload(); });
  $('boot').hidden = true;
  if (!auth.key) { showSignIn(null); return; }
  try { await trySignIn(); } catch (err) {
    auth.clear();
    showSignIn(err);
  }
}

boot();
