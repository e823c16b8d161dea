// The HTTP API from the page: the key (Bearer header, never in a URL), JSON requests with the
// API's error bodies turned into ApiError, authenticated downloads as object URLs, and a job's
// server-sent events read with fetch (EventSource cannot send an Authorization header).

const KEY_NAME = 'dgs.apiKey';

export class ApiError extends Error {
  constructor(status, code, message, retryable = false, details = [], retryAfter = null) {
    super(`${status} ${code}: ${message}`);
    Object.assign(this, { status, code, detail: message, retryable, details, retryAfter });
  }
}

export const auth = {
  key: sessionStorage.getItem(KEY_NAME) || localStorage.getItem(KEY_NAME) || '',
  set(key, remember) {
    this.key = key;
    sessionStorage.setItem(KEY_NAME, key);
    if (remember) localStorage.setItem(KEY_NAME, key);
  },
  clear() {
    this.key = '';
    sessionStorage.removeItem(KEY_NAME);
    localStorage.removeItem(KEY_NAME);
  },
  headers(extra = {}) {
    return this.key ? { Authorization: `Bearer ${this.key}`, ...extra } : { ...extra };
  },
};

/** The API's error body of a failed response as an ApiError (with its Retry-After, seconds). */
export async function errorOf(response) {
  let body = null;
  try { body = await response.json(); } catch { /* not JSON: a proxy's page */ }
  const e = body && body.error;
  const after = /^\d{1,9}$/.test(response.headers.get('Retry-After') || '')
    ? Number(response.headers.get('Retry-After')) : null;
  if (e) return new ApiError(response.status, e.code, e.message, e.retryable, e.details || [], after);
  return new ApiError(response.status, 'http_error', response.statusText || 'request failed', false,
    [], after);
}

/** fetch with the key; throws ApiError for a 4xx/5xx answer. */
export async function request(method, path, { json, body, headers = {}, signal } = {}) {
  const init = { method, headers: auth.headers(headers), signal };
  if (json !== undefined) {
    init.body = JSON.stringify(json);
    init.headers['Content-Type'] = 'application/json';
  } else if (body !== undefined) {
    init.body = body;
  }
  const r = await fetch(path, init);
  if (!r.ok) throw await errorOf(r);
  return r;
}

export async function getJson(path, opts) {
  return (await request('GET', path, opts)).json();
}

/** Statuses a submit is sent again after, as the client library (service/client/http.py). */
const RETRIED = [429, 500, 502, 503, 504];
const SUBMIT_ATTEMPTS = 5;
/** Longest wait after a 429, whatever its Retry-After says (as the client library's max_wait). */
const MAX_WAIT_S = 60;
const sleep = (ms) => new Promise((done) => { setTimeout(done, ms); });

/** The seconds a 429 (a limit of the server, which did nothing) asks to wait; null otherwise. */
function limitWait(err) {
  if (!(err instanceof ApiError) || err.status !== 429) return null;
  return Math.min(err.retryAfter ?? 1, MAX_WAIT_S);
}

/** Wait `seconds`, telling `onWait(seconds left, err)` each second so the page can show it. */
async function waitOut(seconds, err, onWait) {
  for (let left = Math.ceil(seconds); left > 0; left--) {
    if (onWait) onWait(left, err);
    await sleep(1000);
  }
}

/** A request that changes something (cancel, retry, delete), sent again after a 429 once its
 * Retry-After has passed (`onWait` shows the wait), as many times as a submit. */
export async function sendJson(method, path, json, { onWait } = {}) {
  for (let attempt = 0; ; attempt++) {
    try {
      const r = await request(method, path, { json });
      return r.status === 204 ? null : r.json();
    } catch (err) {
      const wait = limitWait(err);
      if (wait === null || attempt + 1 >= SUBMIT_ATTEMPTS) throw err;
      await waitOut(wait, err, onWait);
    }
  }
}

/** A new Idempotency-Key: a UUID (crypto.randomUUID needs a secure context; over plain http
 * beyond localhost it is built from getRandomValues, version 4 like the client library's). */
export function newKey() {
  if (crypto.randomUUID) return crypto.randomUUID();
  const b = crypto.getRandomValues(new Uint8Array(16));
  b[6] = (b[6] & 0x0f) | 0x40;
  b[8] = (b[8] & 0x3f) | 0x80;
  const h = [...b].map((x) => x.toString(16).padStart(2, '0')).join('');
  return `${h.slice(0, 8)}-${h.slice(8, 12)}-${h.slice(12, 16)}-${h.slice(16, 20)}-${h.slice(20)}`;
}

/** POST a submit (a job, a render, an export) with one Idempotency-Key for every attempt: sent
 * again after a lost connection or a retryable answer, 0.5 s apart doubling (after a 429, once
 * its Retry-After has passed, shown by `onWait(seconds left, err)`), so however many of the
 * attempts arrive the server makes one job. Returns the answer's JSON. */
export async function submitJson(path, json, { onWait } = {}) {
  const headers = { 'Idempotency-Key': newKey() };
  for (let attempt = 0; ; attempt++) {
    try {
      return await (await request('POST', path, { json, headers })).json();
    } catch (err) {
      const lost = err instanceof TypeError; // fetch's network failure
      const retried = err instanceof ApiError && RETRIED.includes(err.status);
      if (!(lost || retried) || attempt + 1 >= SUBMIT_ATTEMPTS) throw err;
      const wait = limitWait(err);
      if (wait !== null) await waitOut(wait, err, onWait);
      else await sleep(500 * 2 ** attempt);
    }
  }
}

/** The line a page shows while a 429 is waited out. */
export function waitText(left, err) {
  return `${err.detail} — sending it again in ${left} s`;
}

/** Every item of a paginated listing (`items`, `next_cursor`). */
export async function listAll(path, params = {}) {
  const items = [];
  let cursor = null;
  do {
    const q = new URLSearchParams({ ...params, ...(cursor ? { cursor } : {}) });
    const page = await getJson(`${path}?${q}`);
    items.push(...page.items);
    cursor = page.next_cursor;
  } while (cursor);
  return items;
}

const blobUrls = new Map();

/** An object URL of an authenticated download (kept: artifacts never change). */
export async function blobUrl(path) {
  if (!blobUrls.has(path)) {
    const promise = request('GET', path).then((r) => r.blob()).then((b) => URL.createObjectURL(b));
    blobUrls.set(path, promise);
    promise.catch(() => blobUrls.delete(path));
  }
  return blobUrls.get(path);
}

export async function arrayBuffer(path) {
  return (await request('GET', path)).arrayBuffer();
}

/** One connection's events: yields {id, kind, data} until the server ends the stream. */
async function* eventStream(path, lastEventId, signal) {
  const headers = { Accept: 'text/event-stream' };
  if (lastEventId != null) headers['Last-Event-ID'] = String(lastEventId);
  const r = await request('GET', path, { headers, signal });
  const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = '';
  let fields = {};
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value;
    let nl;
    while ((nl = buffer.search(/\r?\n/)) >= 0) {
      const line = buffer.slice(0, nl);
      buffer = buffer.slice(nl + (buffer[nl] === '\r' ? 2 : 1));
      if (line === '') {
        if ('data' in fields) {
          yield { id: fields.id != null ? Number(fields.id) : null, kind: fields.event || 'message',
                  data: JSON.parse(fields.data) };
        }
        fields = {};
      } else if (!line.startsWith(':')) {
        const i = line.indexOf(':');
        const key = i < 0 ? line : line.slice(0, i);
        let val = i < 0 ? '' : line.slice(i + 1);
        if (val.startsWith(' ')) val = val.slice(1);
        fields[key] = key === 'data' && 'data' in fields ? `${fields.data}\n${val}` : val;
      }
    }
  }
}

const TERMINAL = new Set(['succeeded', 'failed', 'cancelled']);

/** Follow a job's events until it ends, reconnecting with Last-Event-ID when the connection
 *  drops (or, while the server refuses another stream with 429, polling the job until its
 *  Retry-After has passed); `onEvent(event)` for each. Resolves with the final job. */
export async function followJob(jobId, onEvent, signal) {
  let last = null;
  let delay = 500;
  for (;;) {
    let wait = null;
    try {
      for await (const event of eventStream(`/v1/jobs/${jobId}/events`, last, signal)) {
        if (event.id != null) last = event.id;
        delay = 500;
        onEvent(event);
        if (event.kind === 'state' && TERMINAL.has(event.data.state)) {
          return getJson(`/v1/jobs/${jobId}`);
        }
      }
    } catch (err) {
      if (signal && signal.aborted) throw err;
      if (err instanceof ApiError && !err.retryable && err.status < 500) throw err;
      wait = limitWait(err);
    }
    const job = await getJson(`/v1/jobs/${jobId}`);
    if (TERMINAL.has(job.state)) return job;
    await sleep(wait !== null ? wait * 1000 : delay);
    if (wait === null) delay = Math.min(delay * 2, 10000);
  }
}

export function formatBytes(n) {
  const units = ['B', 'KiB', 'MiB', 'GiB', 'TiB'];
  let i = 0;
  while (n >= 1024 && i < units.length - 1) { n /= 1024; i++; }
  return `${n.toFixed(i ? 1 : 0)} ${units[i]}`;
}
