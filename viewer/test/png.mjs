// PNG decoding (8-bit grey/RGB/RGBA, not interlaced: what the Rust renderer and the browser
// write) and the image scores the comparisons use, without a dependency.
import { inflateSync } from 'node:zlib';

export function decodePng(buf) {
  if (buf.readUInt32BE(0) !== 0x89504e47) throw new Error('not a PNG');
  let at = 8;
  let width, height, depth, type, interlace;
  const idat = [];
  while (at < buf.length) {
    const len = buf.readUInt32BE(at);
    const kind = buf.toString('ascii', at + 4, at + 8);
    const data = buf.subarray(at + 8, at + 8 + len);
    if (kind === 'IHDR') {
      width = data.readUInt32BE(0);
      height = data.readUInt32BE(4);
      depth = data[8];
      type = data[9];
      interlace = data[12];
    } else if (kind === 'IDAT') idat.push(data);
    else if (kind === 'IEND') break;
    at += 12 + len;
  }
  const channels = { 0: 1, 2: 3, 4: 2, 6: 4 }[type];
  if (depth !== 8 || !channels || interlace) throw new Error(`unsupported PNG (depth ${depth}, type ${type}, interlace ${interlace})`);
  const raw = inflateSync(Buffer.concat(idat));
  const stride = width * channels;
  const px = new Uint8Array(height * stride);
  for (let y = 0; y < height; y++) {
    const f = raw[y * (stride + 1)];
    const line = raw.subarray(y * (stride + 1) + 1, (y + 1) * (stride + 1));
    for (let x = 0; x < stride; x++) {
      const a = x >= channels ? px[y * stride + x - channels] : 0;
      const b = y > 0 ? px[(y - 1) * stride + x] : 0;
      const c = x >= channels && y > 0 ? px[(y - 1) * stride + x - channels] : 0;
      let v = line[x];
      if (f === 1) v += a;
      else if (f === 2) v += b;
      else if (f === 3) v += (a + b) >> 1;
      else if (f === 4) {
        const p = a + b - c;
        const pa = Math.abs(p - a);
        const pb = Math.abs(p - b);
        const pc = Math.abs(p - c);
        v += pa <= pb && pa <= pc ? a : pb <= pc ? b : c;
      }
      px[y * stride + x] = v & 255;
    }
  }
  // As RGB floats in [0, 1].
  const rgb = new Float64Array(width * height * 3);
  for (let i = 0; i < width * height; i++) {
    for (let k = 0; k < 3; k++) rgb[3 * i + k] = px[i * channels + (channels < 3 ? 0 : k)] / 255;
  }
  return { width, height, rgb };
}

export function psnr(a, b) {
  let se = 0;
  for (let i = 0; i < a.rgb.length; i++) se += (a.rgb[i] - b.rgb[i]) ** 2;
  const mse = se / a.rgb.length;
  return mse === 0 ? Infinity : 10 * Math.log10(1 / mse);
}

/** SSIM on the luma-free RGB mean of 8×8 windows with stride 4 (C1, C2 of Wang et al.). */
export function ssim(a, b) {
  const { width: w, height: h } = a;
  const C1 = 0.01 ** 2;
  const C2 = 0.03 ** 2;
  let sum = 0;
  let n = 0;
  for (let k = 0; k < 3; k++) {
    for (let y = 0; y + 8 <= h; y += 4) {
      for (let x = 0; x + 8 <= w; x += 4) {
        let ma = 0, mb = 0, va = 0, vb = 0, cov = 0;
        for (let j = 0; j < 8; j++) {
          for (let i = 0; i < 8; i++) {
            const p = 3 * ((y + j) * w + x + i) + k;
            ma += a.rgb[p];
            mb += b.rgb[p];
          }
        }
        ma /= 64;
        mb /= 64;
        for (let j = 0; j < 8; j++) {
          for (let i = 0; i < 8; i++) {
            const p = 3 * ((y + j) * w + x + i) + k;
            const da = a.rgb[p] - ma;
            const db = b.rgb[p] - mb;
            va += da * da;
            vb += db * db;
            cov += da * db;
          }
        }
        va /= 63;
        vb /= 63;
        cov /= 63;
        sum += ((2 * ma * mb + C1) * (2 * cov + C2)) / ((ma * ma + mb * mb + C1) * (va + vb + C2));
        n++;
      }
    }
  }
  return sum / n;
}

/** The fraction of pixels whose largest channel difference exceeds `t`. */
export function changedFraction(a, b, t = 0.1) {
  let c = 0;
  for (let i = 0; i < a.width * a.height; i++) {
    let d = 0;
    for (let k = 0; k < 3; k++) d = Math.max(d, Math.abs(a.rgb[3 * i + k] - b.rgb[3 * i + k]));
    if (d > t) c++;
  }
  return c / (a.width * a.height);
}
