// Small helpers the panels share: element lookup, the event bus, status lines.

import { ApiError } from './api.js';

export const $ = (id) => document.getElementById(id);
export const bus = new EventTarget();
export const emit = (name, detail) => bus.dispatchEvent(new CustomEvent(name, { detail }));
export const on = (name, fn) => bus.addEventListener(name, (e) => fn(e.detail));

/** Show `err` (an ApiError or any error) in the status element `el`. */
export function showError(el, err, prefix = '') {
  el.dataset.state = 'error';
  const msg = err instanceof ApiError
    ? `${err.detail}${err.details && err.details.length > 1 ? ` (${err.details.length} problems)` : ''} [HTTP ${err.status} ${err.code}]`
    : String(err && err.message ? err.message : err);
  el.textContent = prefix + msg;
}

export function showStatus(el, text, state = '') {
  el.dataset.state = state;
  el.textContent = text;
}

export function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === 'dataset') Object.assign(node.dataset, v);
    else if (k.startsWith('on')) node.addEventListener(k.slice(2), v);
    else node[k] = v;
  }
  node.append(...children);
  return node;
}
