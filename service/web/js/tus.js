// A resumable uploader speaking tus 1.0.0 (core, creation, checksum, termination) to
// /v1/uploads: one upload per manifest file. The upload URL is remembered in localStorage, so
// a reload (or a dropped network) resumes at the offset the server reports (HEAD) instead of
// sending the file again. Chunks carry Upload-Checksum, so a corrupted chunk is refused and
// sent again rather than stored.

import { ApiError, auth, errorOf } from './api.js';
import { Sha256 } from './sha256.js';

const TUS = { 'Tus-Resumable': '1.0.0' };
const RETRIES = 6;

function b64(text) {
  const bytes = new TextEncoder().encode(text);
  let s = '';
  for (const b of bytes) s += String.fromCharCode(b);
  return btoa(s);
}

async function checksum(buffer) {
  if (globalThis.crypto && crypto.subtle) {
    const digest = new Uint8Array(await crypto.subtle.digest('SHA-256', buffer));
    return `sha256 ${btoa(String.fromCharCode(...digest))}`;
  }
  const hex = new Sha256().update(new Uint8Array(buffer)).hex();
  const raw = hex.match(/../g).map((h) => String.fromCharCode(parseInt(h, 16))).join('');
  return `sha256 ${btoa(raw)}`;
}

const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

export class TusUpload {
  /** `file` (a File or Blob) becomes manifest path `path` of capture `captureId`.
   *  `onProgress(bytesOnServer)` as bytes arrive. */
  constructor(file, { captureId, path, chunkSize = 8 << 20, onProgress = () => {} }) {
    Object.assign(this, { file, captureId, path, chunkSize, onProgress });
    this.storeKey = `dgs.tus:${captureId}:${path}:${file.size}:${file.lastModified || 0}`;
    this.xhr = null;
    this.aborted = false;
  }

  abort() {
    this.aborted = true;
    if (this.xhr) this.xhr.abort();
  }

  async start() {
    this.aborted = false;
    let url = localStorage.getItem(this.storeKey);
    let offset = url ? await this.head(url) : null;
    if (offset == null) {
      url = await this.create();
      offset = 0;
    }
    let failures = 0;
    while (offset < this.file.size) {
      if (this.aborted) throw new ApiError(0, 'aborted', 'upload paused');
      try {
        offset = await this.patch(url, offset);
        failures = 0;
      } catch (err) {
        if (this.aborted) throw new ApiError(0, 'aborted', 'upload paused');
        const retry = !(err instanceof ApiError) || err.retryable || err.status >= 500
          || err.status === 409;
        if (!retry || ++failures > RETRIES) throw err;
        await sleep(Math.min(500 * 2 ** failures, 15000));
        const at = await this.head(url);
        if (at == null) throw err;
        offset = at;
      }
      this.onProgress(offset);
    }
    localStorage.removeItem(this.storeKey);
    this.onProgress(this.file.size);
    return url;
  }

  async create() {
    const r = await fetch('/v1/uploads', {
      method: 'POST',
      headers: auth.headers({ ...TUS, 'Upload-Length': String(this.file.size),
                              'Upload-Metadata': `capture ${b64(this.captureId)},path ${b64(this.path)}` }),
    });
    if (r.status !== 201) throw await errorOf(r);
    const url = r.headers.get('Location');
    localStorage.setItem(this.storeKey, url);
    return url;
  }

  /** The server's offset of `url`, or null when the upload is gone (start a new one). */
  async head(url) {
    const r = await fetch(url, { method: 'HEAD', headers: auth.headers(TUS), cache: 'no-store' });
    if (r.status === 404 || r.status === 410) {
      localStorage.removeItem(this.storeKey);
      return null;
    }
    if (!r.ok) throw new ApiError(r.status, 'http_error', `HEAD ${url} answered ${r.status}`,
                                  r.status >= 500);
    return Number(r.headers.get('Upload-Offset'));
  }

  async patch(url, offset) {
    const end = Math.min(this.file.size, offset + this.chunkSize);
    const chunk = await this.file.slice(offset, end).arrayBuffer();
    const sum = await checksum(chunk);
    return new Promise((resolve, reject) => {
      const xhr = new XMLHttpRequest();
      this.xhr = xhr;
      xhr.open('PATCH', url);
      const headers = auth.headers({ ...TUS, 'Upload-Offset': String(offset),
                                     'Upload-Checksum': sum,
                                     'Content-Type': 'application/offset+octet-stream' });
      for (const [k, v] of Object.entries(headers)) xhr.setRequestHeader(k, v);
      xhr.upload.onprogress = (e) => this.onProgress(offset + e.loaded);
      xhr.onerror = () => reject(new TypeError('network error'));
      xhr.onabort = () => reject(new ApiError(0, 'aborted', 'upload paused'));
      xhr.onload = async () => {
        this.xhr = null;
        if (xhr.status === 204) {
          resolve(Number(xhr.getResponseHeader('Upload-Offset')));
          return;
        }
        let e = null;
        try { e = JSON.parse(xhr.responseText).error; } catch { /* not JSON */ }
        reject(new ApiError(xhr.status, e ? e.code : 'http_error',
                            e ? e.message : `PATCH answered ${xhr.status}`,
                            e ? e.retryable : xhr.status >= 500));
      };
      xhr.send(chunk);
    });
  }
}

/** Terminate an upload the page started (tus termination), e.g. when a file is replaced. */
export async function terminate(url) {
  const r = await fetch(url, { method: 'DELETE', headers: auth.headers(TUS) });
  if (!r.ok && r.status !== 404) throw await errorOf(r);
}
