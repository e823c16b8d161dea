// The relightable sequence stream (.dgss, docs/stream.md) in the page: the header by one HTTP
// range, each group of pictures by another (so playing starts before the file has arrived),
// every chunk checked (magic, group, length, CRC-32) before it is inflated, and decoded frame by
// frame exactly as core.export.codec.GroupDecoder does (integer codes as state, the key space
// deformed by the frame's node transforms, residuals added).

export class StreamError extends Error {}

const PREDICTED = ['means', 'quats', 'normals'];
const ATTRIBUTES = [...PREDICTED, 'scales', 'opacity', 'sh0', 'shN', 'visibility'];
const DTYPES = { i8: Int8Array, u8: Uint8Array, u16: Uint16Array, u32: Uint32Array, i16: Int16Array,
  i32: Int32Array, f32: Float32Array };
const HEAD_GUESS = 65536;

const CRC_TABLE = (() => {
  const t = new Uint32Array(256);
  for (let n = 0; n < 256; n++) {
    let c = n;
    for (let k = 0; k < 8; k++) c = c & 1 ? 0xedb88320 ^ (c >>> 1) : c >>> 1;
    t[n] = c >>> 0;
  }
  return t;
})();

export function crc32(bytes) {
  let c = 0xffffffff;
  for (let i = 0; i < bytes.length; i++) c = CRC_TABLE[(c ^ bytes[i]) & 0xff] ^ (c >>> 8);
  return (c ^ 0xffffffff) >>> 0;
}

const ascii = (bytes) => String.fromCharCode(...bytes);

async function inflate(bytes, where) {
  try {
    const stream = new Blob([bytes]).stream().pipeThrough(new DecompressionStream('deflate'));
    return new Uint8Array(await new Response(stream).arrayBuffer());
  } catch (err) {
    throw new StreamError(`${where}: corrupted (${err.message || err})`);
  }
}

/** The payload of group `group`'s chunk bytes, or StreamError saying what is wrong. */
export async function unpackChunk(raw, group) {
  const where = `group ${group}`;
  if (raw.length < 16 || ascii(raw.subarray(0, 4)) !== 'DGSG') throw new StreamError(`${where}: no chunk header (truncated or not a stream)`);
  const view = new DataView(raw.buffer, raw.byteOffset, raw.byteLength);
  const index = view.getUint32(4, true), length = view.getUint32(8, true), crc = view.getUint32(12, true);
  if (index !== group) throw new StreamError(`${where}: the chunk found there is group ${index}`);
  const body = raw.subarray(16, 16 + length);
  if (body.length < length) throw new StreamError(`${where}: truncated (${body.length} of ${length} bytes)`);
  if (crc32(body) !== crc) throw new StreamError(`${where}: corrupted (CRC-32 mismatch)`);
  return parsePayload(await inflate(body, where), where);
}

function parsePayload(raw, where) {
  const view = new DataView(raw.buffer, raw.byteOffset, raw.byteLength);
  const n = view.getUint32(0, true);
  let table;
  try { table = JSON.parse(new TextDecoder().decode(raw.subarray(4, 4 + n))); } catch {
    throw new StreamError(`${where}: the section table is not JSON`);
  }
  const arrays = {};
  for (const [name, s] of Object.entries(table.sections || {})) {
    const Type = DTYPES[s.dtype];
    const count = s.shape.reduce((a, b) => a * b, 1);
    const start = 4 + n + s.offset, size = count * (Type ? Type.BYTES_PER_ELEMENT : 0);
    if (!Type || start + size > raw.length) throw new StreamError(`${where}: section ${name} runs past the payload`);
    const bytes = new Uint8Array(size);
    const src = raw.subarray(start, start + size), k = Type.BYTES_PER_ELEMENT;
    if (s.shuffle) {
      for (let b = 0; b < k; b++) for (let i = 0; i < count; i++) bytes[i * k + b] = src[b * count + i];
    } else bytes.set(src);
    arrays[name] = new Type(bytes.buffer);
  }
  delete table.sections;
  return { meta: table, arrays, get(name) {
    if (!(name in arrays)) throw new StreamError(`${where}: section ${name} is missing`);
    return arrays[name];
  } };
}

/** A stream at `url`, read by ranges with `fetchRange(url, start, endExclusive)`. */
export class StreamSource {
  constructor(url, fetchRange) {
    this.url = url;
    this.fetchRange = fetchRange;
    this.payloads = new Map();
    this.pending = new Map();
  }

  async open() {
    let head = await this.fetchRange(this.url, 0, HEAD_GUESS);
    if (head.length < 12 || ascii(head.subarray(0, 4)) !== 'DGSS') throw new StreamError('not a dgs stream (no DGSS magic)');
    const view = new DataView(head.buffer, head.byteOffset, head.byteLength);
    const version = view.getUint16(4, true), n = view.getUint32(8, true);
    if (version !== 1) throw new StreamError(`stream version ${version}; this page reads version 1`);
    if (head.length < 12 + n) head = await this.fetchRange(this.url, 0, 12 + n);
    if (head.length < 12 + n) throw new StreamError('the header is truncated');
    try { this.header = JSON.parse(new TextDecoder().decode(head.subarray(12, 12 + n))); } catch {
      throw new StreamError('the header is not JSON');
    }
    this.dataStart = 12 + n;
    this.frameGroup = [];
    for (const g of this.header.groups) for (let i = 0; i < g.count; i++) this.frameGroup.push([g.index, i]);
    return this.header;
  }

  get frames() { return this.frameGroup.length; }

  /** The parsed payload of group `g` (fetched once, by one range request). */
  payload(g) {
    if (this.payloads.has(g)) return Promise.resolve(this.payloads.get(g));
    if (!this.pending.has(g)) {
      const info = this.header.groups[g];
      const start = this.dataStart + info.offset;
      this.pending.set(g, this.fetchRange(this.url, start, start + info.length)
        .then((raw) => unpackChunk(raw, g))
        .then((p) => { this.payloads.set(g, p); this.pending.delete(g); return p; },
              (err) => { this.pending.delete(g); throw err; }));
    }
    return this.pending.get(g);
  }

  has(g) { return this.payloads.has(g); }
}

// -- decoding ------------------------------------------------------------------------------
function grow(a, extra, Type = a.constructor) {
  const out = new Type(a.length + extra.length);
  out.set(a);
  out.set(extra, a.length);
  return out;
}

function quatToMat(q, o, m) { // unit-normalised (w x y z) at q[o..o+3] into m[0..8], row-major
  let w = q[o], x = q[o + 1], y = q[o + 2], z = q[o + 3];
  const l = Math.hypot(w, x, y, z) || 1;
  w /= l; x /= l; y /= l; z /= l;
  m[0] = 1 - 2 * (y * y + z * z); m[1] = 2 * (x * y - w * z); m[2] = 2 * (x * z + w * y);
  m[3] = 2 * (x * y + w * z); m[4] = 1 - 2 * (x * x + z * z); m[5] = 2 * (y * z - w * x);
  m[6] = 2 * (x * z - w * y); m[7] = 2 * (y * z + w * x); m[8] = 1 - 2 * (x * x + y * y);
}

/** Frame-by-frame decoding of one group (core.export.codec.GroupDecoder). */
export class GroupDecoder {
  constructor(payload) {
    const m = payload.meta;
    this.p = payload;
    this.quant = m.quant;
    this.shDim = m.sh_dim;
    this.nodes = payload.get('graph.nodes');
    this.codes = {};
    this.res = {};
    for (const name of ATTRIBUTES) this.codes[name] = Int32Array.from(payload.get(`key.${name}`));
    for (const name of PREDICTED) this.res[name] = new Int32Array(this.codes[name].length);
    this.anchors = Uint16Array.from(payload.get('key.anchors'));
    this.wcodes = Uint8Array.from(payload.get('key.weights'));
    this.ids = Uint32Array.from(payload.get('key.ids'));
    this.alive = new Uint8Array(this.ids.length).fill(1);
    this.index = -1;
    this.count = m.frame_meta.length;
  }

  width(name) { return this.codes[name].length / this.ids.length; }

  births(prefix) {
    const b = this.p.meta.frame_meta[this.index].births;
    if (!b) return;
    for (const name of ATTRIBUTES) this.codes[name] = grow(this.codes[name], this.p.get(`${prefix}.born.${name}`), Int32Array);
    for (const name of PREDICTED) this.res[name] = grow(this.res[name], new Int32Array(b * (this.res[name].length / this.ids.length)));
    this.anchors = grow(this.anchors, this.p.get(`${prefix}.born.anchors`));
    this.wcodes = grow(this.wcodes, this.p.get(`${prefix}.born.weights`));
    this.ids = grow(this.ids, this.p.get(`${prefix}.born.ids`));
    this.alive = grow(this.alive, new Uint8Array(b).fill(1));
  }

  updates(prefix) {
    const S = this.ids.length;
    for (const name of ATTRIBUTES) {
      const key = `${prefix}.upd.${name}`;
      if (!(`${key}.idx` in this.p.arrays)) continue;
      const idx = this.p.get(`${key}.idx`), val = this.p.get(`${key}.val`);
      const target = PREDICTED.includes(name) ? this.res[name] : this.codes[name];
      const c = val.length / idx.length;
      let slot = 0;
      for (let i = 0; i < idx.length; i++) {
        slot += idx[i];
        if (slot >= S) throw new StreamError(`group ${this.p.meta.group}: an update names slot ${slot} of ${S}`);
        for (let k = 0; k < c; k++) target[slot * c + k] += val[i * c + k]; // deltas
      }
    }
  }

  /** The next frame: {count, ids, means, quats, scales, opacityC, opacityG, sh0, shN, normals, visibility}. */
  frame() {
    this.index += 1;
    if (this.index >= this.count) throw new StreamError(`group ${this.p.meta.group} has ${this.count} frames`);
    const prefix = `f${this.index}`;
    let nodeQ = null, nodeT = null;
    if (this.index > 0) {
      const dead = this.p.get(`${prefix}.deaths`);
      let slot = 0;
      for (let i = 0; i < dead.length; i++) { slot += dead[i]; this.alive[slot] = 0; }
      this.births(prefix);
      nodeQ = this.p.get(`${prefix}.node_q`);
      nodeT = this.p.get(`${prefix}.node_t`);
    }
    this.updates(prefix);
    return this.output(nodeQ, nodeT);
  }

  output(nodeQ, nodeT) {
    const S = this.ids.length, q = this.quant, dim = this.shDim;
    let n = 0;
    for (let s = 0; s < S; s++) n += this.alive[s];
    const out = { count: n, ids: new Uint32Array(n), means: new Float32Array(3 * n),
      quats: new Float32Array(4 * n), normals: new Float32Array(3 * n), scales: new Float32Array(3 * n),
      opacityC: new Float32Array(n), opacityG: new Float32Array(n), sh0: new Float32Array(3 * n),
      shN: new Float32Array(3 * dim * n), visibility: new Float32Array(n), shDim: dim };
    const M = nodeQ ? nodeQ.length / 4 : 0, R = new Float32Array(9 * M);
    for (let j = 0; j < M; j++) quatToMat(nodeQ, 4 * j, R.subarray(9 * j, 9 * j + 9));
    const deq = (name, s, k, c) => Math.fround(Math.fround(q[name].lo[q[name].lo.length > 1 ? k : 0])
      + Math.fround(this.codes[name][s * c + k] * q[name].step));
    const tol = { means: q.means.tol, quats: q.quats.tol, normals: q.normals.tol };
    const x = [0, 0, 0], qk = [0, 0, 0, 0], nk = [0, 0, 0], qb = [0, 0, 0, 0], mb = new Float32Array(9);
    let o = 0;
    for (let s = 0; s < S; s++) {
      if (!this.alive[s]) continue;
      // Key-space values, unit, then their residuals (key space too), unit again.
      const rm = this.res.means, rq = this.res.quats, rn = this.res.normals;
      for (let k = 0; k < 3; k++) { x[k] = deq('means', s, k, 3); nk[k] = deq('normals', s, k, 3); }
      for (let k = 0; k < 4; k++) qk[k] = deq('quats', s, k, 4);
      let l = Math.hypot(...qk) || 1;
      for (let k = 0; k < 4; k++) qk[k] = qk[k] / l + rq[4 * s + k] * tol.quats;
      l = Math.hypot(...nk) || 1;
      for (let k = 0; k < 3; k++) { nk[k] = nk[k] / l + rn[3 * s + k] * tol.normals; x[k] += rm[3 * s + k] * tol.means; }
      l = Math.hypot(...qk) || 1;
      for (let k = 0; k < 4; k++) qk[k] /= l;
      l = Math.hypot(...nk) || 1;
      for (let k = 0; k < 3; k++) nk[k] /= l;
      let px = x[0], py = x[1], pz = x[2], pq = qk, pn = nk;
      if (M) {
        const w = [0, 0, 0, 0];
        let total = 0;
        for (let k = 0; k < 4; k++) { w[k] = this.wcodes[4 * s + k]; total += w[k]; }
        for (let k = 0; k < 4; k++) w[k] = total > 0 ? w[k] / total : 0.25;
        px = py = pz = 0;
        qb[0] = qb[1] = qb[2] = qb[3] = 0;
        for (let k = 0; k < 4; k++) {
          const j = this.anchors[4 * s + k], r = 9 * j;
          const gx = this.nodes[3 * j], gy = this.nodes[3 * j + 1], gz = this.nodes[3 * j + 2];
          const dx = x[0] - gx, dy = x[1] - gy, dz = x[2] - gz;
          px += w[k] * (R[r] * dx + R[r + 1] * dy + R[r + 2] * dz + gx + nodeT[3 * j]);
          py += w[k] * (R[r + 3] * dx + R[r + 4] * dy + R[r + 5] * dz + gy + nodeT[3 * j + 1]);
          pz += w[k] * (R[r + 6] * dx + R[r + 7] * dy + R[r + 8] * dz + gz + nodeT[3 * j + 2]);
          for (let c = 0; c < 4; c++) qb[c] += w[k] * nodeQ[4 * j + c];
        }
        const [bw, bx, by, bz] = qb, [aw, ax, ay, az] = qk;
        pq = [bw * aw - bx * ax - by * ay - bz * az, bw * ax + bx * aw + by * az - bz * ay,
          bw * ay - bx * az + by * aw + bz * ax, bw * az + bx * ay - by * ax + bz * aw];
        l = Math.hypot(...qb) || 1;
        for (let c = 0; c < 4; c++) pq[c] /= l;
        quatToMat(qb, 0, mb);
        pn = [mb[0] * nk[0] + mb[1] * nk[1] + mb[2] * nk[2], mb[3] * nk[0] + mb[4] * nk[1] + mb[5] * nk[2],
          mb[6] * nk[0] + mb[7] * nk[1] + mb[8] * nk[2]];
      }
      out.means[3 * o] = px;
      out.means[3 * o + 1] = py;
      out.means[3 * o + 2] = pz;
      l = Math.hypot(...pq) || 1;
      const sign = pq[0] < 0 ? -l : l;
      for (let c = 0; c < 4; c++) out.quats[4 * o + c] = pq[c] / sign;
      l = Math.hypot(...pn) || 1;
      for (let c = 0; c < 3; c++) out.normals[3 * o + c] = pn[c] / l;
      for (let k = 0; k < 3; k++) { out.scales[3 * o + k] = deq('scales', s, k, 3); out.sh0[3 * o + k] = deq('sh0', s, k, 3); }
      out.opacityC[o] = deq('opacity', s, 0, 2);
      out.opacityG[o] = deq('opacity', s, 1, 2);
      out.visibility[o] = deq('visibility', s, 0, 1);
      for (let k = 0; k < 3 * dim; k++) out.shN[3 * dim * o + k] = deq('shN', s, k, 3 * dim);
      out.ids[o] = this.ids[s];
      o += 1;
    }
    return out;
  }
}
