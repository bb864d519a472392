// dualscale view: the exported glTF material on its swatch, a draped cloth or a sphere, with an
// orbiting camera, a movable directional light, false-colour map inspection and, for a digitize
// run, the captured image of an LED beside our renderer's image (served by dualscale.view.server).
// docs/VIEWER.md describes the page, its URL parameters and its test hooks.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const $ = (id) => document.getElementById(id);
const DEG = Math.PI / 180;
const query = new URLSearchParams(location.search);

// texture slots of MeshPhysicalMaterial that GLTFLoader fills from a glTF material
const TEXTURE_SLOTS = ['map', 'roughnessMap', 'metalnessMap', 'normalMap', 'anisotropyMap', 'specularColorMap',
  'specularIntensityMap', 'transmissionMap', 'thicknessMap', 'alphaMap', 'aoMap', 'emissiveMap', 'sheenColorMap',
  'sheenRoughnessMap', 'clearcoatMap', 'clearcoatRoughnessMap', 'clearcoatNormalMap', 'iridescenceMap',
  'iridescenceThicknessMap'];

const state = {
  scene: null,        // scene.json
  exp: null,          // the export shown
  root: null,         // the glTF's scene (the swatch)
  material: null,     // its material (MeshPhysicalMaterial)
  frame: null,        // the swatch's frame: T (image right), B (image up), N, centre, width, height (m)
  repeat: null,       // physical size of one texture repeat [w, h] in metres, and whether it is known
  objects: {},        // swatch, cloth, sphere
  shown: 'swatch',
  sigma: null,        // api/sigma/<key>.json of the export shown (null: no uncertainty)
  showing: 'material', // 'material' or the map whose sigma covers the objects
  originals: new Map(), // mesh -> its own material while a sigma is shown
};

// ---------------------------------------------------------------------------------------------
// renderer, camera, lights

const canvas = $('gl');
const renderer = new THREE.WebGLRenderer({ canvas, antialias: true, preserveDrawingBuffer: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
renderer.outputColorSpace = THREE.SRGBColorSpace;
renderer.toneMapping = THREE.NeutralToneMapping;

const world = new THREE.Scene();
world.background = new THREE.Color(0x303236);
const camera = new THREE.PerspectiveCamera(35, 1, 1e-5, 100);
const controls = new OrbitControls(camera, canvas);
controls.addEventListener('change', requestRender);

const sun = new THREE.DirectionalLight(0xffffff, Math.PI);
world.add(sun, sun.target);
const ambient = new THREE.HemisphereLight(0xffffff, 0x303030, 0.3);
world.add(ambient);

let renderPending = false;
function requestRender() {
  if (renderPending) return;
  renderPending = true;
  requestAnimationFrame(() => { renderPending = false; renderer.render(world, camera); });
}

function resize() {
  const w = canvas.clientWidth || 640, h = canvas.clientHeight || 480;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  camera.updateProjectionMatrix();
  requestRender();
}
new ResizeObserver(resize).observe(canvas);

// ---------------------------------------------------------------------------------------------
// the swatch and its frame

/** The swatch's tangent frame in world space: T = image right (+u), B = image up (-v), N out of
 * the front face; its centre and its extents along T and B in metres. From the first vertex's
 * NORMAL and TANGENT (B = cross(N, T) * w, glTF 2.0 Sec. 3.7.2.1), else from the UVs. */
function swatchFrame(root) {
  root.updateMatrixWorld(true);
  let mesh = null;
  root.traverse((o) => { if (!mesh && o.isMesh) mesh = o; });
  if (!mesh) throw new Error('the glTF has no mesh');
  const g = mesh.geometry;
  const nm = new THREE.Matrix3().getNormalMatrix(mesh.matrixWorld);
  const N = new THREE.Vector3().fromBufferAttribute(g.attributes.normal, 0).applyMatrix3(nm).normalize();
  let T, B;
  if (g.attributes.tangent) {
    const t = new THREE.Vector4().fromBufferAttribute(g.attributes.tangent, 0);
    T = new THREE.Vector3(t.x, t.y, t.z).transformDirection(mesh.matrixWorld);
    B = new THREE.Vector3().crossVectors(N, T).multiplyScalar(t.w < 0 ? -1 : 1);
  } else {
    const idx = g.index ? [0, 1, 2].map((k) => g.index.getX(k)) : [0, 1, 2];
    const p = idx.map((i) => new THREE.Vector3().fromBufferAttribute(g.attributes.position, i).applyMatrix4(mesh.matrixWorld));
    const uv = idx.map((i) => new THREE.Vector2().fromBufferAttribute(g.attributes.uv, i));
    const e1 = p[1].clone().sub(p[0]), e2 = p[2].clone().sub(p[0]);
    const d1 = uv[1].clone().sub(uv[0]), d2 = uv[2].clone().sub(uv[0]);
    const r = 1 / (d1.x * d2.y - d2.x * d1.y);
    T = e1.clone().multiplyScalar(d2.y).sub(e2.clone().multiplyScalar(d1.y)).multiplyScalar(r);
    B = e2.clone().multiplyScalar(d1.x).sub(e1.clone().multiplyScalar(d2.x)).multiplyScalar(-r); // -dP/dv
  }
  T.sub(N.clone().multiplyScalar(N.dot(T))).normalize();
  B.sub(N.clone().multiplyScalar(N.dot(B))).sub(T.clone().multiplyScalar(T.dot(B))).normalize();
  const box = new THREE.Box3().setFromObject(mesh);
  const centre = box.getCenter(new THREE.Vector3());
  const pos = g.attributes.position, q = new THREE.Vector3();
  let t0 = Infinity, t1 = -Infinity, b0 = Infinity, b1 = -Infinity;
  for (let i = 0; i < pos.count; i++) {
    q.fromBufferAttribute(pos, i).applyMatrix4(mesh.matrixWorld).sub(centre);
    const a = q.dot(T), b = q.dot(B);
    t0 = Math.min(t0, a); t1 = Math.max(t1, a); b0 = Math.min(b0, b); b1 = Math.max(b1, b);
  }
  return { mesh, T, B, N, centre, width: t1 - t0, height: b1 - b0 };
}

/** One texture repeat in metres: export.json's repeat_mm, else the glTF's asset extras
 * (dualscale.repeat_mm), else the swatch divided by its texture-transform repeats (unknown scale). */
function repeatSize(exp, json, frame, material) {
  const extras = (json.asset && json.asset.extras && json.asset.extras.dualscale) || {};
  const mm = exp.repeat_mm || extras.repeat_mm;
  if (mm) return { size: [mm[0] / 1000, mm[1] / 1000], known: true };
  const rep = extras.repeats || (material.map ? [material.map.repeat.x, material.map.repeat.y] : [1, 1]);
  return { size: [frame.width / rep[0], frame.height / rep[1]], known: false };
}

/** The anisotropy frame: three.js builds the anisotropy tangent from the mesh's (unperturbed)
 * tangent frame (lights_physical_fragment: anisotropyT = tbn[0] x + tbn[1] y), so with a normal
 * map it is not orthogonal to the shading normal and the anisotropic GGX lobe ignores the
 * normal's tilt. With `shading` on, the tangent is projected onto the plane of the normal-mapped
 * normal (Gram-Schmidt) and B = N x T, as our model does (dualscale.bsdf.mapping.tangent_frame). */
const SHADING_FRAME = `#include <lights_physical_fragment>
#ifdef USE_ANISOTROPY
  material.anisotropyT = normalize( material.anisotropyT - normal * dot( normal, material.anisotropyT ) );
  material.anisotropyB = cross( normal, material.anisotropyT );
#endif`;
function setAnisotropyFrame(m, shading) {
  m.onBeforeCompile = (shader) => {
    if (shading) shader.fragmentShader = shader.fragmentShader.replace('#include <lights_physical_fragment>', SHADING_FRAME);
  };
  m.customProgramCacheKey = () => (shading ? 'dualscale-shading-frame' : 'three');
  m.needsUpdate = true;
}
function applyAnisotropyFrame() {
  const shading = $('aniso-frame').checked;
  const mats = new Set([state.material, ...Object.values(state.objects).map((o) => o.material).filter(Boolean)]);
  for (const m of mats) if (m) setAnisotropyFrame(m, shading);
  requestRender();
}
$('aniso-frame').addEventListener('change', applyAnisotropyFrame);

/** A copy of the glTF material whose textures repeat with the geometry's UVs (in repeats). */
function repeatingMaterial(mat) {
  const m = mat.clone();
  for (const k of TEXTURE_SLOTS) {
    if (!m[k]) continue;
    const t = m[k].clone();
    t.wrapS = t.wrapT = THREE.RepeatWrapping;
    t.repeat.set(1, 1); t.offset.set(0, 0); t.rotation = 0; t.center.set(0, 0);
    t.needsUpdate = true;
    m[k] = t;
  }
  return m;
}

/** Tangents for geometry with glTF-convention UVs (v down the image): computeTangents gives a
 * bitangent along +v (dP/dv); glTF's bitangent is image up, so the handedness w is negated. */
function gltfTangents(geo) {
  geo.computeTangents();
  const t = geo.attributes.tangent;
  for (let i = 0; i < t.count; i++) t.setW(i, -t.getW(i));
  t.needsUpdate = true;
}

/** A square cloth of side S (m) draped over a ball of radius R whose top is at y = R: on the ball
 * up to polar angle a0, then falling along the ball's tangent with folds. UVs in repeats of
 * rep (m), v growing along +z as on the swatch (arc length is kept along the radial lines). */
function clothGeometry(S, R, rep, n = 160) {
  const a0 = 0.42 * Math.PI;
  const pos = [], uv = [], index = [];
  for (let j = 0; j <= n; j++) {
    for (let i = 0; i <= n; i++) {
      const x = (i / n - 0.5) * S, z = (j / n - 0.5) * S;
      const rho = Math.hypot(x, z), phi = Math.atan2(z, x);
      const dx = Math.cos(phi), dz = Math.sin(phi);
      let p;
      if (rho <= R * a0) {
        const a = rho / R;
        p = [R * Math.sin(a) * dx, R * Math.cos(a), R * Math.sin(a) * dz];
      } else {
        const s = rho - R * a0;
        const fold = 0.22 * s * Math.sin(9 * phi);
        p = [R * Math.sin(a0) * dx + s * Math.cos(a0) * dx + fold * dx,
          R * Math.cos(a0) - s * Math.sin(a0),
          R * Math.sin(a0) * dz + s * Math.cos(a0) * dz + fold * dz];
      }
      pos.push(...p);
      uv.push((x + S / 2) / rep[0], (z + S / 2) / rep[1]);
    }
  }
  for (let j = 0; j < n; j++) {
    for (let i = 0; i < n; i++) {
      const a = j * (n + 1) + i, b = a + 1, c = a + n + 1, d = c + 1;
      index.push(a, c, b, b, c, d); // counter-clockwise seen from +y, as the swatch
    }
  }
  const geo = new THREE.BufferGeometry();
  geo.setAttribute('position', new THREE.Float32BufferAttribute(pos, 3));
  geo.setAttribute('uv', new THREE.Float32BufferAttribute(uv, 2));
  geo.setIndex(index);
  geo.computeVertexNormals();
  gltfTangents(geo);
  return geo;
}

/** A sphere of radius R (m), UVs in repeats of rep (m) along the equator and the meridian, image
 * top at the north pole. */
function sphereGeometry(R, rep) {
  const geo = new THREE.SphereGeometry(R, 192, 96);
  const uv = geo.attributes.uv;
  for (let i = 0; i < uv.count; i++) {
    uv.setXY(i, uv.getX(i) * 2 * Math.PI * R / rep[0], (1 - uv.getY(i)) * Math.PI * R / rep[1]);
  }
  gltfTangents(geo);
  return geo;
}

function fmtLength(m) {
  const mm = m * 1000;
  return mm >= 10 ? `${mm.toFixed(0)} mm` : mm >= 1 ? `${mm.toFixed(2)} mm` : `${(mm * 1000).toFixed(0)} µm`;
}

function buildObjects() {
  for (const o of Object.values(state.objects)) world.remove(o);
  const f = state.frame, rep = state.repeat.size;
  const side = Math.max(f.width, f.height);
  const mat = repeatingMaterial(state.material);
  const cloth = new THREE.Mesh(clothGeometry(8 * side, 2 * side, rep), mat);
  const sphere = new THREE.Mesh(sphereGeometry(2 * side, rep), mat);
  sphere.position.set(0, 0, 0);
  cloth.position.set(0, -2 * side, 0);
  state.objects = { swatch: state.root, cloth, sphere };
  state.sizes = {
    swatch: `swatch ${fmtLength(f.width)} × ${fmtLength(f.height)}`,
    cloth: `cloth ${fmtLength(8 * side)} square over a ${fmtLength(4 * side)} ball`,
    sphere: `sphere ${fmtLength(4 * side)} across`,
  };
  for (const o of Object.values(state.objects)) { o.visible = false; world.add(o); }
  showObject(state.shown);
}

function showObject(name) {
  state.shown = name;
  for (const [k, o] of Object.entries(state.objects)) o.visible = k === name;
  const rep = state.repeat;
  $('size-note').textContent = `${state.sizes[name]}; one texture repeat is ` +
    `${fmtLength(rep.size[0])} × ${fmtLength(rep.size[1])}` +
    (rep.known ? '' : ' (scale unknown: the texel size of the capture was not known)');
  resetCamera();
}

function resetCamera() {
  const obj = state.objects[state.shown];
  if (!obj) return;
  const c = new THREE.Box3().setFromObject(obj).getCenter(new THREE.Vector3());
  const mesh = obj.isMesh ? obj : state.frame.mesh;
  mesh.geometry.computeBoundingSphere();
  const r = mesh.geometry.boundingSphere.radius;
  const d = r / Math.sin(Math.min(camera.fov, camera.fov * camera.aspect) * DEG / 2) * 1.05;
  const f = state.frame;
  const dir = f.N.clone().multiplyScalar(Math.cos(35 * DEG)).add(f.B.clone().multiplyScalar(-Math.sin(35 * DEG)));
  camera.position.copy(c).addScaledVector(dir, d);
  camera.near = d / 100; camera.far = d * 100;
  camera.updateProjectionMatrix();
  controls.target.copy(c);
  controls.update();
  sun.target.position.copy(c);
  updateLight();
}

// ---------------------------------------------------------------------------------------------
// the light

/** World direction towards a light at azimuth az (deg, CCW from image +x towards image up) and
 * elevation el (deg above the swatch plane), in the swatch's frame. */
function lightDirection(az, el) {
  const f = state.frame;
  return f.T.clone().multiplyScalar(Math.cos(el * DEG) * Math.cos(az * DEG))
    .addScaledVector(f.B, Math.cos(el * DEG) * Math.sin(az * DEG))
    .addScaledVector(f.N, Math.sin(el * DEG)).normalize();
}

function updateLight() {
  const az = +$('light-az').value, el = +$('light-el').value, e = +$('light-e').value;
  $('light-az-out').textContent = `${az}°`;
  $('light-el-out').textContent = `${el}°`;
  $('light-e-out').textContent = e.toFixed(2);
  $('ambient-out').textContent = (+$('ambient').value).toFixed(2);
  $('exposure-out').textContent = `${(+$('exposure').value).toFixed(1)} EV`;
  ambient.intensity = +$('ambient').value;
  renderer.toneMappingExposure = 2 ** +$('exposure').value;
  sun.intensity = e;
  if (state.frame) {
    const r = camera.position.distanceTo(controls.target) || 1;
    sun.position.copy(sun.target.position).addScaledVector(lightDirection(az, el), r);
  }
  requestRender();
}
for (const id of ['light-az', 'light-el', 'light-e', 'ambient', 'exposure']) $(id).addEventListener('input', updateLight);
$('object-select').addEventListener('change', (e) => showObject(e.target.value));
$('reset-camera').addEventListener('click', resetCamera);

// ---------------------------------------------------------------------------------------------
// map inspection (false colour)

const srgbToLinear = (c) => (c <= 0.04045 ? c / 12.92 : ((c + 0.055) / 1.055) ** 2.4);
const luminance = (r, g, b) => 0.2126 * r + 0.7152 * g + 0.0722 * b;

/** The maps a material carries: [label, texture, value(r, g, b, a in [0, 1]), range or null (auto),
 * cyclic]. Values follow the glTF conventions (docs/EXPORT.md): roughness r (alpha = r^2) in G,
 * anisotropy direction in RG and strength in B, normals 0.5 n + 0.5, colours sRGB-encoded. */
function mapList(m) {
  const list = [];
  if (m.map) {
    const c = m.color;
    list.push(['base colour: luminance (linear)', m.map,
      (r, g, b) => luminance(srgbToLinear(r) * c.r, srgbToLinear(g) * c.g, srgbToLinear(b) * c.b), [0, null]]);
    if (m.transparent) list.push(['opacity (base colour alpha)', m.map, (r, g, b, a) => a * m.opacity, [0, 1]]);
  }
  if (m.roughnessMap) list.push(['roughness r (GGX α = r²)', m.roughnessMap, (r, g) => g * m.roughness, [0, 1]]);
  if (m.normalMap) {
    list.push(['normal: tilt from the surface normal (°)', m.normalMap,
      (r, g, b) => Math.acos(Math.min(1, Math.max(-1, 2 * b - 1))) / DEG, [0, null]]);
    list.push(['normal: tilt azimuth (°, CCW from image right)', m.normalMap,
      (r, g) => ((Math.atan2(2 * g - 1, 2 * r - 1) / DEG) + 360) % 360, [0, 360], true]);
  }
  if (m.anisotropyMap) {
    list.push(['anisotropy strength', m.anisotropyMap, (r, g, b) => b * m.anisotropy, [0, 1]]);
    list.push(['anisotropy direction (°, CCW from image right, mod 180)', m.anisotropyMap,
      (r, g) => ((Math.atan2(2 * g - 1, 2 * r - 1) + m.anisotropyRotation) / DEG + 360) % 180, [0, 180], true]);
  }
  if (m.specularColorMap) {
    const c = m.specularColor;
    list.push(['specular colour: luminance (F0 tint)', m.specularColorMap,
      (r, g, b) => luminance(srgbToLinear(r) * c.r, srgbToLinear(g) * c.g, srgbToLinear(b) * c.b), [0, null]]);
  }
  if (m.specularIntensityMap) list.push(['specular intensity', m.specularIntensityMap, (r, g, b, a) => a * m.specularIntensity, [0, 1]]);
  if (m.transmissionMap) list.push(['transmission weight', m.transmissionMap, (r) => r * m.transmission, [0, 1]]);
  return list;
}

// viridis, polynomial fit (Matt Zucker, CC0), t in [0, 1]
const VIRIDIS = [[0.2777273272234177, 0.005407344544966578, 0.3340998053353061], [0.1050930431085774, 1.404613529898575, 1.384590162594685],
  [-0.3308618287255563, 0.214847559468213, 0.09509516302823659], [-4.634230498983486, -5.799100973351585, -19.33244095627987],
  [6.228269936347081, 14.17993336680509, 56.69055260068105], [4.776384997670288, -13.74514537774601, -65.35303263337234],
  [-5.435455855934631, 4.645852612178535, 26.3124352495832]];
function viridis(t) {
  t = Math.min(1, Math.max(0, t));
  return [0, 1, 2].map((k) => { let v = 0; for (let i = 6; i >= 0; i--) v = v * t + VIRIDIS[i][k]; return Math.min(1, Math.max(0, v)); });
}
function cyclic(t) { // a hue wheel for angles
  const h = (t % 1 + 1) % 1 * 6, x = 1 - Math.abs(h % 2 - 1);
  const rgb = [[1, x, 0], [x, 1, 0], [0, 1, x], [0, x, 1], [x, 0, 1], [1, 0, x]][Math.floor(h) % 6];
  return rgb.map((v) => 0.15 + 0.75 * v);
}

function showMap(k) {
  const entry = state.maps[k];
  if (!entry) return;
  const [label, tex, fn, range, isCyclic] = entry;
  const img = tex.image;
  const w = img.width, h = img.height;
  const src = document.createElement('canvas');
  src.width = w; src.height = h;
  const sctx = src.getContext('2d', { willReadFrequently: true });
  sctx.drawImage(img, 0, 0);
  const px = sctx.getImageData(0, 0, w, h).data;
  const vals = new Float32Array(w * h);
  let lo = Infinity, hi = -Infinity;
  for (let i = 0; i < w * h; i++) {
    const v = fn(px[4 * i] / 255, px[4 * i + 1] / 255, px[4 * i + 2] / 255, px[4 * i + 3] / 255);
    vals[i] = v; lo = Math.min(lo, v); hi = Math.max(hi, v);
  }
  const a = range && range[0] !== null ? range[0] : lo;
  const b = range && range[1] !== null ? range[1] : Math.max(hi, a + 1e-6);
  const out = $('map-canvas');
  out.width = w; out.height = h;
  const octx = out.getContext('2d');
  const data = octx.createImageData(w, h);
  const cmap = isCyclic ? cyclic : viridis;
  for (let i = 0; i < w * h; i++) {
    const c = cmap((vals[i] - a) / (b - a));
    data.data[4 * i] = 255 * c[0]; data.data[4 * i + 1] = 255 * c[1]; data.data[4 * i + 2] = 255 * c[2]; data.data[4 * i + 3] = 255;
  }
  octx.putImageData(data, 0, 0);
  const bar = $('colorbar'), bctx = bar.getContext('2d');
  for (let x = 0; x < bar.width; x++) {
    const c = cmap(x / (bar.width - 1));
    bctx.fillStyle = `rgb(${255 * c[0]},${255 * c[1]},${255 * c[2]})`;
    bctx.fillRect(x, 0, 1, bar.height);
  }
  const fmt = (v) => (Math.abs(v) >= 10 ? v.toFixed(0) : v.toPrecision(3));
  $('map-range').innerHTML = `<span>${fmt(a)}</span><span>${fmt(b)}</span>`;
  $('map-note').textContent = `${label}: ${w} × ${h} texels, values ${fmt(lo)} to ${fmt(hi)}` +
    (state.material.ior !== undefined ? `; IOR ${state.material.ior.toFixed(3)} (one value in glTF)` : '');
}

function fillMaps() {
  state.maps = mapList(state.material);
  const sel = $('map-select');
  sel.replaceChildren(...state.maps.map((m, i) => new Option(m[0], String(i))));
  const prefix = query.get('map');
  const want = prefix === null ? 0 : state.maps.findIndex((m) => m[0].startsWith(prefix));
  if (want < 0 && !state.mapErrorShown) {
    state.mapErrorShown = true;
    urlError(`?map=${prefix}: no map of this material starts so (it has ${state.maps.map((m) => m[0]).join('; ')}); ` +
      `showing ${state.maps.length ? state.maps[0][0] : 'none'}`);
  }
  sel.value = String(want >= 0 ? want : 0);
  showMap(+sel.value);
}
$('map-select').addEventListener('change', (e) => showMap(+e.target.value));

// ---------------------------------------------------------------------------------------------
// per-texel uncertainty (issue 26): the sigma of one map as a false-colour texture on the objects,
// the PNG made by the server with the report's colour map (dualscale.report.plots.sigma_colours)

function meshes() {
  const out = [];
  for (const o of Object.values(state.objects)) o.traverse((c) => { if (c.isMesh) out.push(c); });
  return out;
}

function restoreMaterials() {
  for (const [mesh, mat] of state.originals) mesh.material = mat;
  state.originals.clear();
}

/** A MeshBasicMaterial with the sigma texture placed as the mesh's own base-colour texture is. */
function sigmaMaterial(orig, tex) {
  const t = tex.clone();
  const src = orig.map;
  if (src) {
    t.wrapS = src.wrapS; t.wrapT = src.wrapT; t.repeat.copy(src.repeat); t.offset.copy(src.offset);
    t.rotation = src.rotation; t.center.copy(src.center); t.channel = src.channel;
  } else {
    t.wrapS = t.wrapT = THREE.RepeatWrapping;
  }
  t.needsUpdate = true;
  return new THREE.MeshBasicMaterial({ map: t, toneMapped: false, side: orig.side });
}

const sigmaTextures = new Map();
async function sigmaTexture(url) {
  if (!sigmaTextures.has(url)) {
    const tex = await new THREE.TextureLoader().loadAsync(url);
    tex.flipY = false; // glTF's UVs: v runs down the image, as in the glTF's own textures
    tex.colorSpace = THREE.SRGBColorSpace; // the PNG holds display colours
    tex.magFilter = THREE.NearestFilter;
    sigmaTextures.set(url, tex);
  }
  return sigmaTextures.get(url);
}

async function showSigma(name) {
  const legend = $('sigma-legend');
  const entry = name === 'material' || !state.sigma ? null : state.sigma.maps.find((m) => m.name === name);
  restoreMaterials();
  if (!entry) {
    state.showing = 'material';
    $('show-select').value = 'material';
    legend.hidden = true;
    requestRender();
    return;
  }
  const tex = await sigmaTexture(entry.url);
  for (const mesh of meshes()) {
    state.originals.set(mesh, mesh.material);
    mesh.material = sigmaMaterial(mesh.material, tex);
  }
  state.showing = name;
  $('show-select').value = name;
  const bar = $('sigma-bar'), bctx = bar.getContext('2d'), cols = state.sigma.colorbar;
  for (let x = 0; x < bar.width; x++) {
    const c = cols[Math.min(cols.length - 1, Math.floor(x * cols.length / bar.width))];
    bctx.fillStyle = `rgb(${c[0]},${c[1]},${c[2]})`;
    bctx.fillRect(x, 0, 1, bar.height);
  }
  const fmt = (v) => (v === null ? 'undetermined' : Math.abs(v) >= 10 ? v.toFixed(0) : v.toPrecision(3));
  const unit = entry.unit === 'map value' ? '' : ` ${entry.unit}`;
  $('sigma-range').innerHTML = '';
  $('sigma-range').append(...[`0${unit}`, `${fmt(entry.vmax)}${unit}${entry.clipped > 0 ? ' and above' : ''}`]
    .map((t) => Object.assign(document.createElement('span'), { textContent: t })));
  const und = state.sigma.undetermined;
  $('sigma-und-swatch').style.background = und.colour;
  const med = entry.median.length === 1 ? fmt(entry.median[0]) :
    entry.median.map((v, i) => `${'RGB'[i]} ${fmt(v)}`).join(', ');
  $('sigma-text').textContent = `undetermined (${(100 * entry.undetermined_fraction).toFixed(1)} % of texels) in ` +
    `${und.name}. ${entry.label}: 1σ in ${entry.units}` + (entry.channels > 1 ? ' (largest channel per texel)' : '') +
    `, colour map ${state.sigma.colormap} from 0; median ${med}.`;
  legend.hidden = false;
  requestRender();
}

/** The show: select of an export: its sigma maps, or absent and disabled without uncertainty. */
async function setupSigma(exp) {
  const sel = $('show-select');
  state.sigma = null;
  state.showing = 'material';
  state.originals.clear(); // the objects were rebuilt with the export's own materials
  $('sigma-legend').hidden = true;
  sel.replaceChildren(new Option('material', 'material'));
  if (!exp.sigma) {
    sel.disabled = true;
    $('show-label').hidden = true;
    return;
  }
  state.sigma = await fetchJSON(exp.sigma);
  sel.append(...state.sigma.maps.map((m) => new Option(m.label, m.name)));
  sel.disabled = false;
  $('show-label').hidden = false;
}
$('show-select').addEventListener('change', (e) => showSigma(e.target.value).catch(fail));

// ---------------------------------------------------------------------------------------------
// captured vs. our renderer

async function fetchJSON(url) {
  const r = await fetch(url);
  const doc = await r.json();
  if (!r.ok) throw new Error(doc.error || `${url}: HTTP ${r.status}`);
  return doc;
}

async function showLed(id) {
  $('led-info').textContent = `rendering LED ${id}…`;
  const info = await fetchJSON(`api/led/${id}.json`);
  const load = (img, url) => new Promise((ok, fail) => { img.onload = ok; img.onerror = () => fail(new Error(`${url} did not load`)); img.src = url; });
  await Promise.all([load($('img-captured'), info.captured), load($('img-rendered'), info.rendered)]);
  state.led = info;
  $('led-info').textContent = `LED ${info.led}: θ ${info.theta_deg.toFixed(1)}°, φ ${info.phi_deg.toFixed(1)}°; ` +
    `${info.size[0]} × ${info.size[1]} px, one exposure for both (×${info.display_scale.toPrecision(3)}); ` +
    `our render differs from the capture by ${(100 * info.rel_error).toFixed(1)} % (Σ|render − capture| / Σ capture)`;
}

function setupLeds(scene) {
  if (!scene.side_by_side) {
    $('led-absent').hidden = false;
    $('led-absent').textContent = `No side-by-side: ${scene.no_capture}.`;
    return null;
  }
  $('led-panel').hidden = false;
  const sel = $('led-select');
  sel.replaceChildren(...scene.leds.map((l) => new Option(`LED ${l.id}: θ ${l.theta_deg.toFixed(0)}°, φ ${l.phi_deg.toFixed(0)}°`, String(l.id))));
  const want = query.get('led');
  if (want !== null && scene.leds.some((l) => String(l.id) === want)) sel.value = want;
  sel.addEventListener('change', () => showLed(+sel.value).catch(fail));
  $('led-light').addEventListener('click', () => {
    const l = scene.leds.find((x) => String(x.id) === sel.value);
    $('light-az').value = Math.round(l.phi_deg);
    $('light-el').value = Math.max(1, Math.round(90 - l.theta_deg));
    updateLight();
  });
  return showLed(+sel.value);
}

// ---------------------------------------------------------------------------------------------
// loading

function fail(err) {
  $('status').textContent = `error: ${err.message}`;
  $('status').classList.add('error');
  console.error(err);
}

/** Fetches a .gltf's external buffers with fetch().arrayBuffer() instead of three's FileLoader,
 * which re-streams the body for progress events: headless Chromium then reported about one load
 * in eight of the .glb or .bin as aborted (the page was intact), a false failure for the tests. */
class FetchBuffers {
  constructor(parser) { this.parser = parser; this.name = 'dualscale_fetch_buffers'; this.buffers = new Map(); }

  loadBufferView(index) {
    const json = this.parser.json, view = json.bufferViews[index], def = json.buffers[view.buffer];
    if (def.uri === undefined) return null; // the GLB's own chunk: three's parser
    if (!this.buffers.has(view.buffer)) {
      const url = new URL(def.uri, new URL(this.parser.options.path || '', location.href)).href;
      this.buffers.set(view.buffer, fetch(url).then((r) => {
        if (!r.ok) throw new Error(`${url}: HTTP ${r.status}`);
        return r.arrayBuffer();
      }));
    }
    const off = view.byteOffset || 0;
    return this.buffers.get(view.buffer).then((b) => b.slice(off, off + (view.byteLength || 0)));
  }
}

const loader = new GLTFLoader();
loader.register((parser) => new FetchBuffers(parser));

async function loadExport(exp) {
  $('status').textContent = `loading ${exp.name}…`;
  // fetched here rather than by GLTFLoader.loadAsync (see FetchBuffers)
  const resp = await fetch(exp.url);
  if (!resp.ok) throw new Error(`${exp.url}: HTTP ${resp.status}`);
  const gltf = await loader.parseAsync(await resp.arrayBuffer(), exp.url.slice(0, exp.url.lastIndexOf('/') + 1));
  if (state.root) world.remove(state.root);
  state.exp = exp;
  state.root = gltf.scene;
  state.frame = swatchFrame(gltf.scene);
  state.material = state.frame.mesh.material;
  state.repeat = repeatSize(exp, gltf.parser.json, state.frame, state.material);
  buildObjects();
  applyAnisotropyFrame();
  fillMaps();
  await setupSigma(exp);
  $('status').textContent = `${exp.name} (${exp.key})`;
}

// ---------------------------------------------------------------------------------------------
// URL parameters (docs/VIEWER.md): each one is checked; a bad one is a visible error naming it,
// what it accepts and what is shown instead, never a blank view or a silent default.

const PARAMS = ['export', 'object', 'az', 'el', 'e', 'map', 'led', 'frame'];
const urlErrors = [];

function urlError(text) {
  urlErrors.push(text);
  const box = $('url-error');
  box.hidden = false;
  box.replaceChildren(...urlErrors.map((t) => Object.assign(document.createElement('div'), { textContent: t })));
  console.warn(`dualscale view: ${text}`);
}

/** The value of a number parameter of a range input (az, el, e), or null when absent or bad
 * (then an error says why and the default stays). */
function numberParam(name, input) {
  const raw = query.get(name);
  if (raw === null) return null;
  const lo = +input.min, hi = +input.max, v = raw.trim() === '' ? NaN : Number(raw);
  if (!Number.isFinite(v) || v < lo || v > hi) {
    urlError(`?${name}=${raw}: not a number from ${lo} to ${hi}; keeping ${input.value}`);
    return null;
  }
  return v;
}

/** Check the URL's parameters against the scene before anything is shown; sets the controls of
 * the good ones and returns the export to load. */
function applyQuery(scene) {
  for (const k of new Set(query.keys())) {
    if (!PARAMS.includes(k)) urlError(`?${k}: not a parameter of this page (it takes ${PARAMS.join(', ')})`);
  }
  let first = scene.exports[0];
  const ek = query.get('export');
  if (ek !== null) {
    const e = scene.exports.find((x) => x.key === ek);
    if (e) first = e;
    else urlError(`?export=${ek}: this folder has no such export (it has ${scene.exports.map((x) => x.key).join(', ')}); ` +
      `showing ${first.key}`);
  }
  const frame = query.get('frame');
  if (frame === 'three') $('aniso-frame').checked = false;
  else if (frame !== null && frame !== 'ours') urlError(`?frame=${frame}: choose three or ours; showing ours`);
  const obj = query.get('object');
  if (obj !== null) {
    const names = Array.from($('object-select').options, (o) => o.value);
    if (names.includes(obj)) $('object-select').value = state.shown = obj;
    else urlError(`?object=${obj}: not an object of this page (choose ${names.join(', ')}); showing ${state.shown}`);
  }
  for (const [k, id] of [['az', 'light-az'], ['el', 'light-el'], ['e', 'light-e']]) {
    const v = numberParam(k, $(id));
    if (v !== null) $(id).value = String(v);
  }
  return first;
}

/** ?led=K against the scene's LEDs (after the side-by-side is set up). */
function checkLedParam(scene) {
  const want = query.get('led');
  if (want === null) return;
  if (!scene.side_by_side) urlError(`?led=${want}: no side-by-side here (${scene.no_capture})`);
  else if (!scene.leds.some((l) => String(l.id) === want)) {
    const ids = scene.leds.map((l) => l.id);
    urlError(`?led=${want}: the dataset has no such LED (it has ${ids.length} LEDs, ids ${ids[0]} to ` +
      `${ids[ids.length - 1]}); showing LED ${$('led-select').value}`);
  }
}

async function main() {
  const scene = await fetchJSON('scene.json');
  state.scene = scene;
  document.title = `dualscale view: ${scene.title}`;
  $('title').textContent = `dualscale view: ${scene.title}`;
  const sel = $('export-select');
  sel.replaceChildren(...scene.exports.map((e) => new Option(`${e.key}: ${e.name}`, e.key)));
  sel.addEventListener('change', () => loadExport(scene.exports.find((e) => e.key === sel.value)).catch(fail));
  const first = applyQuery(scene);
  sel.value = first.key;
  resize();
  await loadExport(first);
  const leds = setupLeds(scene);
  checkLedParam(scene);
  await leds;
}

// ---------------------------------------------------------------------------------------------
// test hooks (docs/VIEWER.md): the flat swatch seen straight down by an orthographic camera
// under one directional light, no ambient, no tone mapping, read back as linear floats.

/** Render the swatch alone, straight down along its normal (image right = +x, image up = +y),
 * under a directional light of irradiance E (three.js: radiance = BRDF * E * cos) from
 * (az, el) in the swatch frame, into a float target of width x height; returns linear RGB rows
 * top to bottom. */
function renderFlat({ az, el, irradiance, width, height }) {
  const f = state.frame;
  const sc = new THREE.Scene();
  const swatch = state.root.clone();
  sc.add(swatch);
  const light = new THREE.DirectionalLight(0xffffff, irradiance);
  light.position.copy(f.centre).addScaledVector(lightDirection(az, el), 1);
  light.target.position.copy(f.centre);
  sc.add(light, light.target);
  const d = Math.max(f.width, f.height);
  const cam = new THREE.OrthographicCamera(-f.width / 2, f.width / 2, f.height / 2, -f.height / 2, d / 100, 3 * d);
  cam.position.copy(f.centre).addScaledVector(f.N, d);
  cam.up.copy(f.B);
  cam.lookAt(f.centre);
  cam.updateMatrixWorld(true);
  const rt = new THREE.WebGLRenderTarget(width, height, { type: THREE.FloatType, minFilter: THREE.NearestFilter, magFilter: THREE.NearestFilter });
  const tm = renderer.toneMapping;
  renderer.toneMapping = THREE.NoToneMapping;
  renderer.setRenderTarget(rt);
  renderer.setClearColor(0x000000, 0);
  renderer.clear();
  renderer.render(sc, cam);
  const buf = new Float32Array(width * height * 4);
  renderer.readRenderTargetPixels(rt, 0, 0, width, height, buf);
  renderer.setRenderTarget(null);
  renderer.toneMapping = tm;
  rt.dispose();
  const out = new Array(width * height * 3);
  for (let y = 0; y < height; y++) { // GL rows run bottom to top
    const src = (height - 1 - y) * width;
    for (let x = 0; x < width; x++) for (let c = 0; c < 3; c++) out[3 * (y * width + x) + c] = buf[4 * (src + x) + c];
  }
  requestRender();
  return { width, height, rgb: out };
}

const ready = main().then(() => { $('status').dataset.ready = '1'; return true; }, (err) => { fail(err); return false; });

window.dualscaleViewer = {
  ready,
  renderFlat,
  /** What the page loaded: texture size, swatch size (m), repeat (m) and the material's glTF extensions. */
  info: () => ({
    export: state.exp && state.exp.key,
    texture: state.material && state.material.map ? [state.material.map.image.width, state.material.map.image.height] : null,
    swatch_m: state.frame && [state.frame.width, state.frame.height],
    repeat_m: state.repeat && state.repeat.size,
    maps: (state.maps || []).map((m) => m[0]),
    objects: Object.keys(state.objects),
    led: state.led || null,
    url_errors: urlErrors.slice(),
    sigma: state.sigma ? state.sigma.maps.map((m) => m.name) : [],
    showing: state.showing,
  }),
  show: (name) => { $('object-select').value = name; showObject(name); },
  showMap: (i) => { $('map-select').value = String(i); showMap(i); },
  /** Show map `name`'s sigma on the objects ('material': the material again); resolves when shown. */
  showSigma: (name) => showSigma(name).then(() => state.showing),
  render: () => renderer.render(world, camera),
  /** Anisotropy frame: true = orthogonal to the normal-mapped normal (ours), false = three.js's. */
  setShadingFrame: (on) => { $('aniso-frame').checked = !!on; applyAnisotropyFrame(); },
};
