// Reads a viewer folder as `lifegom-reconstruct --viewer` writes it (docs/export.md, "The
// viewer folder"): `avatar.json` names every binary file with its length and every array with
// its file, offset, type and shape. Anything missing or short is one error naming the file.

export const FORMAT = 'lifegom-viewer';
export const VERSION = 1;

export class ViewerDataError extends Error {}

async function fetchBytes(base, name) {
  let res;
  try {
    res = await fetch(new URL(name, base));
  } catch (e) {
    throw new ViewerDataError(`${name}: could not be read (${e.message})`);
  }
  if (!res.ok) throw new ViewerDataError(`${name}: missing (HTTP ${res.status})`);
  return new Uint8Array(await res.arrayBuffer());
}

async function fetchJson(base, name) {
  const bytes = await fetchBytes(base, name);
  try {
    return JSON.parse(new TextDecoder().decode(bytes));
  } catch (e) {
    throw new ViewerDataError(`${name}: not valid JSON (${e.message})`);
  }
}

function field(obj, name, file, check) {
  const v = obj?.[name];
  if (v === undefined || (check && !check(v))) throw new ViewerDataError(`${file}: field \`${name}\` is missing or invalid`);
  return v;
}

const isCount = (v) => Number.isInteger(v) && v >= 0;

/** Loads the manifest, every file it names, the views and the motions. */
export async function loadViewerData(base) {
  const manifest = await fetchJson(base, 'avatar.json');
  const m = 'avatar.json';
  if (manifest.format !== FORMAT || manifest.version !== VERSION) {
    throw new ViewerDataError(`${m}: not a ${FORMAT} version ${VERSION} manifest (format ${manifest.format}, version ${manifest.version})`);
  }
  const files = field(manifest, 'files', m, (v) => typeof v === 'object');
  const bytes = {};
  await Promise.all(
    Object.entries(files).map(async ([name, len]) => {
      const b = await fetchBytes(base, name);
      if (b.length !== len) {
        throw new ViewerDataError(`${name}: ${b.length} bytes, ${m} says ${len} (${b.length < len ? 'truncated' : 'too long'})`);
      }
      bytes[name] = b;
    }),
  );
  const arrays = field(manifest, 'arrays', m, (v) => typeof v === 'object');
  const array = (name, dtype, shape) => {
    const a = field(arrays, name, m);
    const where = `${m}: array \`${name}\``;
    if (a.dtype !== dtype) throw new ViewerDataError(`${where}: dtype ${a.dtype}, expected ${dtype}`);
    if (JSON.stringify(a.shape) !== JSON.stringify(shape)) {
      throw new ViewerDataError(`${where}: shape ${JSON.stringify(a.shape)}, expected ${JSON.stringify(shape)}`);
    }
    const file = bytes[a.file];
    if (!file) throw new ViewerDataError(`${where}: file \`${a.file}\` is not listed under \`files\``);
    const count = shape.reduce((x, y) => x * y, 1);
    if (!isCount(a.offset) || a.offset % 4 !== 0 || a.offset + 4 * count > file.length) {
      throw new ViewerDataError(`${a.file}: array \`${name}\` (offset ${a.offset}, ${4 * count} bytes) runs past the end of the file`);
    }
    // The file's buffer is freshly allocated by fetch, so its start is aligned.
    const Type = dtype === 'f32' ? Float32Array : Uint32Array;
    return new Type(file.buffer, file.byteOffset + a.offset, count);
  };
  const counts = field(manifest, 'counts', m);
  const V = field(counts, 'lowres_vertices', m, isCount);
  const F = field(counts, 'lowres_faces', m, isCount);
  const N = field(counts, 'gaussians', m, isCount);
  const J = field(counts, 'joints', m, isCount);
  const skeleton = field(manifest, 'skeleton', m);
  const names = field(skeleton, 'names', m, (v) => Array.isArray(v) && v.length === J);
  const parents = field(skeleton, 'parents', m, (v) => Array.isArray(v) && v.length === J && v.every((p) => Number.isInteger(p) && p < J));
  const rest = field(skeleton, 'rest_joints', m, (v) => Array.isArray(v) && v.length === J).flat();
  const avatar = {
    subject: manifest.subject ?? '',
    background: field(manifest, 'background', m, (v) => Array.isArray(v) && v.length === 3),
    subdivision: field(manifest, 'subdivision', m, isCount),
    lowresVertices: V,
    lowresFaces: F,
    gaussians: N,
    joints: J,
    skeleton: { names, parents, rest },
    xyz: array('lowres_xyz', 'f32', [V, 3]),
    faces: array('lowres_faces', 'u32', [F, 3]),
    weights: array('skin_weights', 'f32', [V, J]),
    face: array('gaussian_face', 'u32', [N]),
    bary: array('gaussian_bary', 'f32', [N, 3, 3]),
    so3: array('gaussian_so3', 'f32', [N, 3]),
    scales: array('gaussian_scales', 'f32', [N, 3]),
    offsets: array('gaussian_offsets', 'f32', [N, 3]),
    colors: array('gaussian_colors', 'f32', [N, 3]),
    opacities: array('gaussian_opacities', 'f32', [N]),
  };
  for (let g = 0; g < N; g++) {
    if (avatar.face[g] >= F) throw new ViewerDataError(`${arrays.gaussian_face.file}: Gaussian ${g} rides on face ${avatar.face[g]} of ${F}`);
  }
  for (let i = 0; i < 3 * F; i++) {
    if (avatar.faces[i] >= V) throw new ViewerDataError(`${arrays.lowres_faces.file}: face ${Math.floor(i / 3)} has corner ${avatar.faces[i]} of ${V} vertices`);
  }
  const motions = field(manifest, 'motions', m, Array.isArray).map((mo, k) => {
    const name = field(mo, 'name', `${m}: motions[${k}]`, (v) => typeof v === 'string');
    const frames = field(mo, 'frames', `${m}: motion \`${name}\``, (v) => isCount(v) && v > 0);
    const fps = field(mo, 'fps', `${m}: motion \`${name}\``, (v) => typeof v === 'number' && v > 0);
    return { name, fps, frames, poses: array(field(mo, 'array', `${m}: motion \`${name}\``), 'f32', [frames, J, 3]) };
  });
  const views = await fetchJson(base, 'views.json');
  const list = field(views, 'views', 'views.json', (v) => Array.isArray(v) && v.length > 0);
  list.forEach((v, k) => {
    const where = `views.json: views[${k}]`;
    field(v, 'name', where, (x) => typeof x === 'string');
    field(v, 'width', where, (x) => isCount(x) && x > 0);
    field(v, 'height', where, (x) => isCount(x) && x > 0);
    field(v, 'K', where, (x) => Array.isArray(x) && x.length === 3 && x.every((r) => r.length === 3));
    field(v, 'E', where, (x) => Array.isArray(x) && x.length >= 3 && x.every((r) => r.length === 4));
  });
  return { avatar, motions, views: list, pivot: views.pivot ?? [0, 0, 0] };
}
