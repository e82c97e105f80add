// Gaussians-on-Mesh posing for the browser, the same math as lifegom's renderer
// (docs/design.md §4.2-§4.3 and §5.2-§5.4; render/src/skeleton.rs, render/src/gom/cpu.rs).
//
// Split so that the per-frame work on the CPU is the rig only: forward kinematics of the
// joints and linear blend skinning of the few thousand low-res vertices, then one texel triple
// per low-res face (its posed corner and two edges). Every Gaussian's constants (where its
// triangle sits inside its low-res ancestor, its offset and local covariance) are computed
// once at load into a second texture, and the GPU rebuilds each posed Gaussian from the two
// in a Spark covariance modifier (`gomModifier`), once per pose change.

// Gaussians (and faces) per texture row. A row of Gaussians is 5 × 1024 = 5120 texels wide,
// within the maximum texture size of every WebGL2 device we target (SwiftShader's is 8192);
// the page checks it at load.
export const PER_ROW = 1024;
export const GAUSSIAN_TEXELS = 5;
export const FACE_TEXELS = 3;

/** Axis-angle to a row-major 3x3, exactly as lifegom's `rodrigues` (the `|v| + 1e-5` guard). */
export function rodrigues(x, y, z) {
  const theta = Math.hypot(x, y, z);
  const d = theta + 1e-5;
  const rx = x / d;
  const ry = y / d;
  const rz = z / d;
  const s = Math.sin(theta);
  const c1 = 1 - Math.cos(theta);
  // K = [[0, -rz, ry], [rz, 0, -rx], [-ry, rx, 0]]; R = I + s K + (1 - c) K².
  const k = [0, -rz, ry, rz, 0, -rx, -ry, rx, 0];
  const k2 = mul3(k, k);
  const r = new Array(9);
  for (let i = 0; i < 9; i++) r[i] = (i % 4 === 0 ? 1 : 0) + s * k[i] + c1 * k2[i];
  return r;
}

function mul3(a, b) {
  const out = new Array(9);
  for (let i = 0; i < 3; i++) {
    for (let j = 0; j < 3; j++) {
      out[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
    }
  }
  return out;
}

/** Joints in an order where parents come first (lifegom does not require it of the file). */
export function topologicalOrder(parents) {
  const order = [];
  const state = new Uint8Array(parents.length);
  const visit = (i) => {
    if (state[i] === 2) return;
    if (state[i] === 1) throw new Error(`joint ${i} is its own ancestor`);
    state[i] = 1;
    if (parents[i] >= 0) visit(parents[i]);
    state[i] = 2;
    order.push(i);
  };
  for (let i = 0; i < parents.length; i++) visit(i);
  return order;
}

/**
 * Skinning transforms `M_i = G_i · Trans(−J_i)` of a pose (`pose`: J×3 axis-angles, or null for
 * the zero pose), as 12 floats per joint (row-major 3×4), in f64 like lifegom's forward
 * kinematics.
 */
export function skinningTransforms(skeleton, pose, out) {
  const { parents, rest, order } = skeleton;
  const n = parents.length;
  const rot = skeleton.scratchRot ?? (skeleton.scratchRot = new Float64Array(9 * n));
  const tr = skeleton.scratchTr ?? (skeleton.scratchTr = new Float64Array(3 * n));
  for (const i of order) {
    const r = pose ? rodrigues(pose[3 * i], pose[3 * i + 1], pose[3 * i + 2]) : [1, 0, 0, 0, 1, 0, 0, 0, 1];
    const p = parents[i];
    const jx = rest[3 * i];
    const jy = rest[3 * i + 1];
    const jz = rest[3 * i + 2];
    if (p < 0) {
      for (let k = 0; k < 9; k++) rot[9 * i + k] = r[k];
      tr[3 * i] = jx;
      tr[3 * i + 1] = jy;
      tr[3 * i + 2] = jz;
    } else {
      const lx = jx - rest[3 * p];
      const ly = jy - rest[3 * p + 1];
      const lz = jz - rest[3 * p + 2];
      for (let a = 0; a < 3; a++) {
        for (let b = 0; b < 3; b++) {
          rot[9 * i + 3 * a + b] =
            rot[9 * p + 3 * a] * r[b] + rot[9 * p + 3 * a + 1] * r[3 + b] + rot[9 * p + 3 * a + 2] * r[6 + b];
        }
        tr[3 * i + a] =
          rot[9 * p + 3 * a] * lx + rot[9 * p + 3 * a + 1] * ly + rot[9 * p + 3 * a + 2] * lz + tr[3 * p + a];
      }
    }
  }
  for (let i = 0; i < n; i++) {
    const jx = rest[3 * i];
    const jy = rest[3 * i + 1];
    const jz = rest[3 * i + 2];
    for (let a = 0; a < 3; a++) {
      const r0 = rot[9 * i + 3 * a];
      const r1 = rot[9 * i + 3 * a + 1];
      const r2 = rot[9 * i + 3 * a + 2];
      out[12 * i + 4 * a] = r0;
      out[12 * i + 4 * a + 1] = r1;
      out[12 * i + 4 * a + 2] = r2;
      out[12 * i + 4 * a + 3] = tr[3 * i + a] - (r0 * jx + r1 * jy + r2 * jz);
    }
  }
  return out;
}

/** The non-zero skinning weights of each low-res vertex, from the dense `[V, J]` table. */
export function sparseWeights(dense, numVertices, numJoints) {
  const start = new Uint32Array(numVertices + 1);
  const joints = [];
  const weights = [];
  for (let v = 0; v < numVertices; v++) {
    start[v] = joints.length;
    for (let j = 0; j < numJoints; j++) {
      const w = dense[v * numJoints + j];
      if (w !== 0) {
        joints.push(j);
        weights.push(w);
      }
    }
  }
  start[numVertices] = joints.length;
  return { start, joints: Uint16Array.from(joints), weights: Float64Array.from(weights) };
}

/** `x' = Σ_j w_j (R_j x + t_j)` for every low-res vertex, without dividing by Σ w (§4.3). */
export function skinVertices(rest, skin, transforms, out) {
  const { start, joints, weights } = skin;
  const n = start.length - 1;
  for (let v = 0; v < n; v++) {
    const x = rest[3 * v];
    const y = rest[3 * v + 1];
    const z = rest[3 * v + 2];
    let px = 0;
    let py = 0;
    let pz = 0;
    for (let k = start[v]; k < start[v + 1]; k++) {
      const m = 12 * joints[k];
      const w = weights[k];
      px += w * (transforms[m] * x + transforms[m + 1] * y + transforms[m + 2] * z + transforms[m + 3]);
      py += w * (transforms[m + 4] * x + transforms[m + 5] * y + transforms[m + 6] * z + transforms[m + 7]);
      pz += w * (transforms[m + 8] * x + transforms[m + 9] * y + transforms[m + 10] * z + transforms[m + 11]);
    }
    out[3 * v] = px;
    out[3 * v + 1] = py;
    out[3 * v + 2] = pz;
  }
  return out;
}

/** Per low-res face: its first corner and the two edges from it (RGBA texels, w unused). */
export function writeFaceFrames(vertices, faces, texels) {
  const f = faces.length / 3;
  for (let i = 0; i < f; i++) {
    const a = 3 * faces[3 * i];
    const b = 3 * faces[3 * i + 1];
    const c = 3 * faces[3 * i + 2];
    const at = 4 * (Math.floor(i / PER_ROW) * PER_ROW * FACE_TEXELS + (i % PER_ROW) * FACE_TEXELS);
    for (let k = 0; k < 3; k++) {
      texels[at + k] = vertices[a + k];
      texels[at + 4 + k] = vertices[b + k] - vertices[a + k];
      texels[at + 8 + k] = vertices[c + k] - vertices[a + k];
    }
  }
  return texels;
}

/**
 * The constant part of every Gaussian (computed once, at load), as five RGBA texels:
 * its triangle's centroid and Steiner semi-diameters `f1 = (v2 − c)/2`, `f2 = (v1 − v0)/(2√3)`
 * in the coordinates of its low-res ancestor's two edges (corners are fixed barycentric
 * combinations of the ancestor's corners in every pose, §5.2, so these are too), its offset,
 * its local covariance `R S Sᵀ Rᵀ` (§5.4), its ancestor's index, its colour and opacity.
 */
export function gaussianTexels(a) {
  const n = a.gaussians;
  const rowTexels = PER_ROW * GAUSSIAN_TEXELS;
  const rows = Math.max(1, Math.ceil(n / PER_ROW));
  const t = new Float32Array(4 * rowTexels * rows);
  const inv2s3 = 1 / (2 * Math.sqrt(3));
  for (let g = 0; g < n; g++) {
    const b = a.bary.subarray(9 * g, 9 * g + 9);
    // Corner c = P0 + u_c e1 + v_c e2 with (u_c, v_c) = (b[c][1], b[c][2]): rows sum to 1.
    const u = [b[1], b[4], b[7]];
    const v = [b[2], b[5], b[8]];
    const cu = (u[0] + u[1] + u[2]) / 3;
    const cv = (v[0] + v[1] + v[2]) / 3;
    const f1u = (u[2] - cu) / 2;
    const f1v = (v[2] - cv) / 2;
    const f2u = (u[1] - u[0]) * inv2s3;
    const f2v = (v[1] - v[0]) * inv2s3;
    const r = so3Exp(a.so3[3 * g], a.so3[3 * g + 1], a.so3[3 * g + 2]);
    const s = [a.scales[3 * g], a.scales[3 * g + 1], a.scales[3 * g + 2]];
    // L = (R S)(R S)ᵀ, symmetric.
    const m = [r[0] * s[0], r[1] * s[1], r[2] * s[2], r[3] * s[0], r[4] * s[1], r[5] * s[2], r[6] * s[0], r[7] * s[1], r[8] * s[2]];
    const l = (i, j) => m[3 * i] * m[3 * j] + m[3 * i + 1] * m[3 * j + 1] + m[3 * i + 2] * m[3 * j + 2];
    const o = [a.offsets[3 * g], a.offsets[3 * g + 1], a.offsets[3 * g + 2]];
    const at = 4 * (Math.floor(g / PER_ROW) * rowTexels + (g % PER_ROW) * GAUSSIAN_TEXELS);
    t.set([cu, cv, f1u, f1v, f2u, f2v, o[0], o[1], o[2], l(0, 0), l(0, 1), l(0, 2), l(1, 1), l(1, 2), l(2, 2), a.face[g]], at);
    t.set([a.colors[3 * g], a.colors[3 * g + 1], a.colors[3 * g + 2], a.opacities[g]], at + 16);
  }
  return { data: t, width: rowTexels, height: rows };
}

/** `exp(hat(r))` as pytorch3d's `so3_exp_map` (θ² floored at 1e-4), row-major. */
export function so3Exp(x, y, z) {
  const nrm2 = x * x + y * y + z * z;
  const theta = Math.sqrt(Math.max(nrm2, 1e-4));
  const fac1 = Math.sin(theta) / theta;
  const fac2 = (1 - Math.cos(theta)) / (theta * theta);
  const k = [0, -z, y, z, 0, -x, -y, x, 0];
  const k2 = [x * x - nrm2, x * y, x * z, y * x, y * y - nrm2, y * z, z * x, z * y, z * z - nrm2];
  const r = new Array(9);
  for (let i = 0; i < 9; i++) r[i] = (i % 4 === 0 ? 1 : 0) + fac1 * k[i] + fac2 * k2[i];
  return r;
}

// The GPU half: one posed Gaussian from its constants and its ancestor's posed corner and
// edges, the Steiner frame exactly as render/src/gom/cpu.rs builds it (the half-angle form of
// t0 = ½·atan2(y, x), the degenerate-triangle shift, the 1e-24 normal guard, σ = 1 mm).
export const GOM_GLSL = /* glsl */ `
vec4 gomTexel(sampler2D t, int i, int k, int per) {
  return texelFetch(t, ivec2((i & ${PER_ROW - 1}) * per + k, i >> ${Math.log2(PER_ROW)}), 0);
}

void gomPose(sampler2D gs, sampler2D fs, int g, out vec3 center, out vec3 xxyyzz, out vec3 xyxzyz, out vec4 rgba) {
  vec4 t0 = gomTexel(gs, g, 0, ${GAUSSIAN_TEXELS});
  vec4 t1 = gomTexel(gs, g, 1, ${GAUSSIAN_TEXELS});
  vec4 t2 = gomTexel(gs, g, 2, ${GAUSSIAN_TEXELS});
  vec4 t3 = gomTexel(gs, g, 3, ${GAUSSIAN_TEXELS});
  rgba = gomTexel(gs, g, 4, ${GAUSSIAN_TEXELS});
  int face = int(t3.w + 0.5);
  vec3 p0 = gomTexel(fs, face, 0, ${FACE_TEXELS}).xyz;
  vec3 e1 = gomTexel(fs, face, 1, ${FACE_TEXELS}).xyz;
  vec3 e2 = gomTexel(fs, face, 2, ${FACE_TEXELS}).xyz;
  vec3 c = p0 + t0.x * e1 + t0.y * e2;
  vec3 f1 = t0.z * e1 + t0.w * e2;
  vec3 f2 = t1.x * e1 + t1.y * e2;
  float f11 = dot(f1, f1);
  float f22 = dot(f2, f2);
  float y = 2.0 * dot(f1, f2);
  float x = f11 - f22;
  bool degenerate = x * x + y * y <= (f11 + f22) * (f11 + f22) * 1e-12 + 1e-30;
  float xs = degenerate ? x + 1.0 : x;
  float r = length(vec2(xs, y));
  float cs = 1.0;
  float sn = 0.0;
  if (r > 0.0) {
    if (xs >= 0.0) {
      cs = sqrt((r + xs) / (2.0 * r));
      sn = y / (2.0 * r * cs);
    } else {
      // copysign(·, y), the sign bit included (y = -0 gives t0 = -π/2, as atan2 does).
      float sgn = (floatBitsToUint(y) & 0x80000000u) != 0u ? -1.0 : 1.0;
      sn = sqrt((r - xs) / (2.0 * r)) * sgn;
      cs = y / (2.0 * r * sn);
    }
  }
  vec3 a0 = f1 * cs + f2 * sn;
  vec3 a1 = f2 * cs - f1 * sn;
  vec3 n = cross(a0, a1);
  float nrm = sqrt(dot(n, n) + 1e-24);
  mat3 A = mat3(2.0 * a0, 2.0 * a1, n * (1e-3 / nrm));
  center = c + A * vec3(t1.z, t1.w, t2.x);
  mat3 L = mat3(t2.y, t2.z, t2.w, t2.z, t3.x, t3.y, t2.w, t3.y, t3.z);
  mat3 S = A * L * transpose(A);
  xxyyzz = vec3(S[0][0], S[1][1], S[2][2]);
  xyxzyz = vec3(S[1][0], S[2][0], S[2][1]);
}
`;
