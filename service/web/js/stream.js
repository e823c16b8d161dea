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

  /** Dequantized attribute `name` of every slot: float32(lo + float32(code * step)), as numpy. */
  values(name) {
    const q = this.quant[name], codes = this.codes[name], out = new Float32Array(codes.length);
    const c = codes.length / this.ids.length, step = Math.fround(q.step);
    const lo = Float32Array.from({ length: c }, (_, k) => q.lo[q.lo.length > 1 ? k : 0]);
    for (let i = 0; i < codes.length; i++) out[i] = lo[i % c] + Math.fround(codes[i] * step);
    return out;
  }

  output(nodeQ, nodeT) {
    const S = this.ids.length, dim = this.shDim, q = this.quant;
    let n = 0;
    for (let s = 0; s < S; s++) n += this.alive[s];
    const out = { count: n, ids: new Uint32Array(n), means: new Float32Array(3 * n),
      quats: new Float32Array(4 * n), normals: new Float32Array(3 * n), scales: new Float32Array(3 * n),
      opacityC: new Float32Array(n), opacityG: new Float32Array(n), sh0: new Float32Array(3 * n),
      shN: new Float32Array(3 * dim * n), visibility: new Float32Array(n), shDim: dim };
    const M = nodeQ ? nodeQ.length / 4 : 0, R = new Float32Array(9 * M), mb = new Float32Array(9);
    for (let j = 0; j < M; j++) quatToMat(nodeQ, 4 * j, R.subarray(9 * j, 9 * j + 9));
    const X = this.values('means'), Q = this.values('quats'), N = this.values('normals');
    const SC = this.values('scales'), OP = this.values('opacity'), C0 = this.values('sh0');
    const SH = this.values('shN'), VI = this.values('visibility');
    const rm = this.res.means, rq = this.res.quats, rn = this.res.normals;
    const tm = q.means.tol, tq = q.quats.tol, tn = q.normals.tol, w = [0, 0, 0, 0], qb = [0, 0, 0, 0];
    let o = 0;
    for (let s = 0; s < S; s++) {
      if (!this.alive[s]) continue;
      // Key-space values, unit, plus their residuals (key space too), unit again.
      let l = Math.sqrt(Q[4 * s] ** 2 + Q[4 * s + 1] ** 2 + Q[4 * s + 2] ** 2 + Q[4 * s + 3] ** 2) || 1;
      let qw = Q[4 * s] / l + rq[4 * s] * tq, qx = Q[4 * s + 1] / l + rq[4 * s + 1] * tq;
      let qy = Q[4 * s + 2] / l + rq[4 * s + 2] * tq, qz = Q[4 * s + 3] / l + rq[4 * s + 3] * tq;
      l = Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) || 1;
      qw /= l; qx /= l; qy /= l; qz /= l;
      l = Math.sqrt(N[3 * s] ** 2 + N[3 * s + 1] ** 2 + N[3 * s + 2] ** 2) || 1;
      let nx = N[3 * s] / l + rn[3 * s] * tn, ny = N[3 * s + 1] / l + rn[3 * s + 1] * tn;
      let nz = N[3 * s + 2] / l + rn[3 * s + 2] * tn;
      l = Math.sqrt(nx * nx + ny * ny + nz * nz) || 1;
      nx /= l; ny /= l; nz /= l;
      const x0 = X[3 * s] + rm[3 * s] * tm, x1 = X[3 * s + 1] + rm[3 * s + 1] * tm;
      const x2 = X[3 * s + 2] + rm[3 * s + 2] * tm;
      let px = x0, py = x1, pz = x2;
      if (M) {
        let total = 0;
        for (let k = 0; k < 4; k++) { w[k] = this.wcodes[4 * s + k]; total += w[k]; }
        for (let k = 0; k < 4; k++) w[k] = total > 0 ? w[k] / total : 0.25;
        px = py = pz = 0;
        qb[0] = qb[1] = qb[2] = qb[3] = 0;
        for (let k = 0; k < 4; k++) {
          const j = this.anchors[4 * s + k], r = 9 * j, wk = w[k];
          const gx = this.nodes[3 * j], gy = this.nodes[3 * j + 1], gz = this.nodes[3 * j + 2];
          const dx = x0 - gx, dy = x1 - gy, dz = x2 - gz;
          px += wk * (R[r] * dx + R[r + 1] * dy + R[r + 2] * dz + gx + nodeT[3 * j]);
          py += wk * (R[r + 3] * dx + R[r + 4] * dy + R[r + 5] * dz + gy + nodeT[3 * j + 1]);
          pz += wk * (R[r + 6] * dx + R[r + 7] * dy + R[r + 8] * dz + gz + nodeT[3 * j + 2]);
          for (let c = 0; c < 4; c++) qb[c] += wk * nodeQ[4 * j + c];
        }
        l = Math.sqrt(qb[0] ** 2 + qb[1] ** 2 + qb[2] ** 2 + qb[3] ** 2) || 1;
        const bw = qb[0] / l, bx = qb[1] / l, by = qb[2] / l, bz = qb[3] / l;
        const aw = qw, ax = qx, ay = qy, az = qz;
        qw = bw * aw - bx * ax - by * ay - bz * az;
        qx = bw * ax + bx * aw + by * az - bz * ay;
        qy = bw * ay - bx * az + by * aw + bz * ax;
        qz = bw * az + bx * ay - by * ax + bz * aw;
        quatToMat(qb, 0, mb);
        const ax2 = nx, ay2 = ny, az2 = nz;
        nx = mb[0] * ax2 + mb[1] * ay2 + mb[2] * az2;
        ny = mb[3] * ax2 + mb[4] * ay2 + mb[5] * az2;
        nz = mb[6] * ax2 + mb[7] * ay2 + mb[8] * az2;
      }
      out.means[3 * o] = px; out.means[3 * o + 1] = py; out.means[3 * o + 2] = pz;
      l = Math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz) || 1;
      if (qw < 0) l = -l;
      out.quats[4 * o] = qw / l; out.quats[4 * o + 1] = qx / l;
      out.quats[4 * o + 2] = qy / l; out.quats[4 * o + 3] = qz / l;
      l = Math.sqrt(nx * nx + ny * ny + nz * nz) || 1;
      out.normals[3 * o] = nx / l; out.normals[3 * o + 1] = ny / l; out.normals[3 * o + 2] = nz / l;
      for (let k = 0; k < 3; k++) { out.scales[3 * o + k] = SC[3 * s + k]; out.sh0[3 * o + k] = C0[3 * s + k]; }
      out.opacityC[o] = OP[2 * s];
      out.opacityG[o] = OP[2 * s + 1];
      out.visibility[o] = VI[s];
      out.shN.set(SH.subarray(3 * dim * s, 3 * dim * (s + 1)), 3 * dim * o);
      out.ids[o] = this.ids[s];
      o += 1;
    }
    return out;
  }
}
