#!/usr/bin/env node
// An independent oracle for glTF 2.0 animation, skinning and morph targets: three.js (its GLTFLoader
// and AnimationMixer), run in Node, writes the world-space vertex positions of every mesh primitive
// of an asset's default scene at the given times of one animation.
//
//   node tests/three_pose.mjs ASSET.(gltf|glb) --animation K|NAME|none --times t1,t2,... --out OUT.json
//
// three is taken from JAXPBR_THREE (the package's folder), else from the checkout's node_modules
// (`npm install --no-save --no-package-lock three@0.170.0`, as .ci/run does); it is imported by
// absolute file URL, so the script runs from any working directory.
//
// Output: {"three": version, "asset": path, "scene": index,
//          "animation": {"index", "name", "duration"} | null, "times": [...],
//          "primitives": [{"node", "mesh", "primitive", "kind", "count", "positions": [[[x, y, z], ...] per time]}],
//          "skipped": [{"node", "mesh", "why"}], "notes": [...]}   (exit 2: bad arguments or asset,
//          3: three not installed, 4: GLTFLoader failed, 1: anything else)
//
// What it does, and where three departs from the glTF specification (see also tests/three_oracle.py):
// - images, textures and samplers are stripped from a copy of the JSON (and every material texture
//   reference), so no image is decoded; buffers are read from disk (URIs relative to the asset, or
//   data: URIs, or the GLB BIN chunk).
// - A morph target without POSITION (beside others that have one) is loaded by GLTFLoader r170 with
//   the base positions as its displacement (morphTargetsRelative is set); this script replaces such
//   a target by zeros, as the specification says (a missing attribute displaces nothing).
// - A `weights` channel: GLTFLoader binds it to every object with morph targets under the node, so
//   descendant nodes' meshes follow it too (and two such channels are averaged); where that would
//   happen this script makes the weights tracks again for each channel's own node only.
// - EXT_mesh_gpu_instancing nodes (three's InstancedMesh) are skipped and listed in "skipped";
//   KHR_draco_mesh_compression is not supported (no DRACOLoader); EXT_meshopt_compression is.
// - The clip is played LoopOnce with clampWhenFinished and the action is reset before each
//   mixer.setTime(t): t < 0 poses at 0, t > duration at the duration (the clip's duration is the
//   largest last key of its channels), and a channel before its first key / after its last holds
//   its first / last value, as the specification says.
// - Vertex positions: Mesh.getVertexPosition (morph targets, relative, weights as they are, not
//   normalised), then for a SkinnedMesh the bone transform (JOINTS_0/WEIGHTS_0 only, the weights
//   renormalised to sum 1 by GLTFLoader, bind matrix identity), then matrixWorld.
import fs from 'node:fs';
import path from 'node:path';
import { fileURLToPath, pathToFileURL } from 'node:url';

const HERE = path.dirname(fileURLToPath(import.meta.url));
const USAGE = 'usage: node tests/three_pose.mjs ASSET.(gltf|glb) --animation K|NAME|none --times t1,t2,... --out OUT.json';

function fail(message, code = 2) {
  process.stderr.write(`three_pose: ${message}\n`);
  process.exit(code);
}

function parseArgs(argv) {
  const out = { asset: null, animation: null, times: null, out: null };
  for (let i = 0; i < argv.length; i++) {
    const a = argv[i];
    const value = () => {
      if (i + 1 >= argv.length) fail(`${a} needs a value\n${USAGE}`);
      return argv[++i];
    };
    if (a === '--animation') out.animation = value();
    else if (a === '--times') out.times = value();
    else if (a === '--out') out.out = value();
    else if (a === '-h' || a === '--help') { process.stdout.write(USAGE + '\n'); process.exit(0); }
    else if (a.startsWith('--')) fail(`unknown option ${a}\n${USAGE}`);
    else if (out.asset === null) out.asset = a;
    else fail(`more than one asset given (${out.asset}, ${a})\n${USAGE}`);
  }
  if (out.asset === null) fail(`no asset given\n${USAGE}`);
  if (out.animation === null) fail(`--animation is required (an index, a name, or none)\n${USAGE}`);
  if (out.times === null) fail(`--times is required (comma-separated seconds)\n${USAGE}`);
  if (out.out === null) fail(`--out is required\n${USAGE}`);
  const times = out.times.split(',').map((s) => s.trim()).filter((s) => s.length > 0);
  if (times.length === 0) fail(`--times has no time in it: ${JSON.stringify(out.times)}`);
  out.times = times.map((s) => {
    const t = Number(s);
    if (!Number.isFinite(t)) fail(`--times: ${JSON.stringify(s)} is not a finite number`);
    return t;
  });
  return out;
}

async function importThree() {
  const dir = process.env.JAXPBR_THREE || path.resolve(HERE, '..', 'node_modules', 'three');
  if (!fs.existsSync(path.join(dir, 'package.json'))) {
    fail(`three is not installed at ${dir} (npm install --no-save --no-package-lock three@0.170.0 in the checkout, or set JAXPBR_THREE)`, 3);
  }
  // The real path: GLTFLoader imports 'three' by the package's own name, which Node resolves to
  // the real path; the same URL here keeps one instance of the module.
  const real = fs.realpathSync(dir);
  const version = JSON.parse(fs.readFileSync(path.join(real, 'package.json'), 'utf8')).version;
  const url = (p) => pathToFileURL(path.join(real, p)).href;
  const THREE = await import(url('build/three.module.js'));
  const { GLTFLoader } = await import(url('examples/jsm/loaders/GLTFLoader.js'));
  return { THREE, GLTFLoader, version, dir: real, url };
}

// ---------------------------------------------------------------------------------------------
// The asset: its JSON (textures stripped) and a reader of its buffers
// ---------------------------------------------------------------------------------------------
function readAsset(file) {
  let bytes;
  try {
    bytes = fs.readFileSync(file);
  } catch (e) {
    fail(`cannot read ${file}: ${e.message}`);
  }
  let json;
  let bin = null;
  if (bytes.length >= 12 && bytes.toString('latin1', 0, 4) === 'glTF') {
    const version = bytes.readUInt32LE(4);
    if (version !== 2) fail(`${file}: GLB version ${version}, not 2`);
    const length = Math.min(bytes.readUInt32LE(8), bytes.length);
    let offset = 12;
    while (offset + 8 <= length) {
      const chunkLength = bytes.readUInt32LE(offset);
      const chunkType = bytes.readUInt32LE(offset + 4);
      const body = bytes.subarray(offset + 8, offset + 8 + chunkLength);
      if (chunkType === 0x4e4f534a) json = JSON.parse(body.toString('utf8'));
      else if (chunkType === 0x004e4942 && bin === null) bin = body;
      offset += 8 + chunkLength;
    }
    if (json === undefined) fail(`${file}: GLB without a JSON chunk`);
  } else {
    try {
      json = JSON.parse(bytes.toString('utf8'));
    } catch (e) {
      fail(`${file}: neither a GLB nor JSON: ${e.message}`);
    }
  }
  return { json, bin };
}

const TEXTURE_ONLY_EXTENSIONS = ['KHR_texture_basisu', 'EXT_texture_webp', 'EXT_texture_avif', 'KHR_texture_transform', 'MSFT_texture_dds'];

function stripTextures(json) {
  delete json.images;
  delete json.textures;
  delete json.samplers;
  const strip = (obj) => {
    if (Array.isArray(obj)) { obj.forEach(strip); return; }
    if (obj === null || typeof obj !== 'object') return;
    for (const key of Object.keys(obj)) {
      const v = obj[key];
      if (/texture$/i.test(key) && v !== null && typeof v === 'object' && !Array.isArray(v) && 'index' in v) delete obj[key];
      else strip(v);
    }
  };
  strip(json.materials || []);
  for (const key of ['extensionsUsed', 'extensionsRequired']) {
    if (json[key]) json[key] = json[key].filter((e) => !TEXTURE_ONLY_EXTENSIONS.includes(e));
  }
}

function toArrayBuffer(buf) {
  return buf.buffer.slice(buf.byteOffset, buf.byteOffset + buf.byteLength);
}

function loadBufferBytes(json, index, assetDir, bin) {
  const def = json.buffers[index];
  if (def.uri === undefined) {
    if (bin === null) throw new Error(`buffer ${index} has no uri and the asset has no GLB BIN chunk`);
    return toArrayBuffer(bin);
  }
  const uri = def.uri;
  if (uri.startsWith('data:')) {
    const comma = uri.indexOf(',');
    if (comma < 0) throw new Error(`buffer ${index}: malformed data URI`);
    const header = uri.slice(5, comma);
    const payload = uri.slice(comma + 1);
    const data = /;base64$/i.test(header) ? Buffer.from(payload, 'base64') : Buffer.from(decodeURIComponent(payload), 'latin1');
    return toArrayBuffer(data);
  }
  const file = path.resolve(assetDir, decodeURIComponent(uri));
  try {
    return toArrayBuffer(fs.readFileSync(file));
  } catch (e) {
    throw new Error(`buffer ${index}: cannot read ${file}: ${e.message}`);
  }
}

// ---------------------------------------------------------------------------------------------
// The objects three made of each glTF node's mesh primitives
// ---------------------------------------------------------------------------------------------
async function primitiveObjects(parser, json, sceneIndex) {
  // The glTF nodes of the scene, depth first (parser.getDependency('node', i) is cached: it is the
  // object in the scene).
  const scene = (json.scenes || [])[sceneIndex];
  const nodeIds = [];
  const seen = new Set();
  const walk = (i) => {
    if (seen.has(i)) return;
    seen.add(i);
    nodeIds.push(i);
    for (const c of json.nodes[i].children || []) walk(c);
  };
  for (const i of (scene && scene.nodes) || []) walk(i);
  const nodeObjects = new Map();
  for (const i of nodeIds) nodeObjects.set(i, await parser.getDependency('node', i));
  const isNodeObject = new Set(nodeObjects.values());
  const found = [];
  const skipped = [];
  for (const i of nodeIds) {
    const nodeDef = json.nodes[i];
    if (nodeDef.mesh === undefined) continue;
    const root = nodeObjects.get(i);
    // The primitives' objects: the node's object itself (a one-primitive mesh), or below it (a
    // Group of primitives, or a Group that also holds a camera), never into another glTF node.
    // (parser.associations is not used for the node index: three shares one association record
    // between the clones of a mesh used by several nodes, so its `nodes` is the last one's.)
    const prims = [];
    const visit = (obj, depth) => {
      if (obj !== root && isNodeObject.has(obj)) return;
      const a = parser.associations.get(obj);
      if (a && a.meshes === nodeDef.mesh && a.primitives !== undefined && obj.geometry) prims.push(obj);
      if (depth < 2) for (const c of obj.children) visit(c, depth + 1);
    };
    visit(root, 0);
    const expected = json.meshes[nodeDef.mesh].primitives.length;
    if (nodeDef.extensions && nodeDef.extensions.EXT_mesh_gpu_instancing) {
      // three's InstancedMesh (its EXT_mesh_gpu_instancing plugin) carries no association: skipped.
      skipped.push({ node: i, mesh: nodeDef.mesh, why: 'EXT_mesh_gpu_instancing (three makes InstancedMesh objects): not posed by this oracle' });
      continue;
    }
    for (const obj of prims) {
      found.push({ node: i, mesh: nodeDef.mesh, primitive: parser.associations.get(obj).primitives, object: obj });
    }
    if (prims.length !== expected) {
      skipped.push({ node: i, mesh: nodeDef.mesh, why: `three made ${prims.length} of the mesh's ${expected} primitives` });
    }
  }
  found.sort((a, b) => a.node - b.node || a.primitive - b.primitive);
  return { found, skipped };
}

function zeroMissingMorphPositions(THREE, json, found, notes) {
  const done = new Set();
  for (const { mesh, primitive, object } of found) {
    const targets = json.meshes[mesh].primitives[primitive].targets;
    const morph = object.geometry.morphAttributes.position;
    if (!targets || !morph || done.has(object.geometry)) continue;
    done.add(object.geometry);
    targets.forEach((t, k) => {
      if (t.POSITION === undefined && morph[k]) {
        morph[k] = new THREE.Float32BufferAttribute(new Float32Array(morph[k].count * 3), 3);
        const note = `mesh ${mesh} primitive ${primitive}: morph target ${k} has no POSITION; zeros used (GLTFLoader would displace by the base positions)`;
        if (!notes.includes(note)) notes.push(note);
      }
    });
  }
}

// GLTFLoader binds a `weights` channel to every object with morph targets under the node, so the
// meshes of its descendant nodes follow it too (and two such channels are averaged). Where that
// happens the clip's weights tracks are made again, each for its own node's primitives only, with
// GLTFLoader's own track maker (the same keys, interpolation and CUBICSPLINE interpolant).
async function ownWeightsTracks(parser, json, animIndex, clip, found, notes) {
  const def = json.animations[animIndex];
  const byNode = new Map();
  for (const f of found) {
    if (!byNode.has(f.node)) byNode.set(f.node, []);
    byNode.get(f.node).push(f.object);
  }
  const channels = def.channels.filter((c) => c.target.node !== undefined && c.target.path === 'weights');
  let leaks = false;
  for (const c of channels) {
    const own = new Set(byNode.get(c.target.node) || []);
    const nodeObject = await parser.getDependency('node', c.target.node);
    nodeObject.traverse((o) => { if (o.morphTargetInfluences && !own.has(o)) leaks = true; });
  }
  if (!leaks) return;
  const tracks = clip.tracks.filter((t) => !t.name.endsWith('.morphTargetInfluences'));
  for (const c of channels) {
    const sampler = def.samplers[c.sampler];
    const objects = (byNode.get(c.target.node) || []).filter((o) => o.morphTargetInfluences);
    const proxy = { name: '', uuid: '', traverse: (fn) => objects.forEach(fn) };
    const input = await parser.getDependency('accessor', sampler.input);
    const output = await parser.getDependency('accessor', sampler.output);
    const made = parser._createAnimationTracks(proxy, input, output, sampler, c.target);
    made.forEach((t, j) => { t.name = `${objects[j].uuid}.morphTargetInfluences`; }); // (names need not be unique)
    tracks.push(...made);
  }
  clip.tracks = tracks;
  clip.resetDuration();
  notes.push(`animation ${animIndex}: weights channels re-bound to their own nodes' primitives (GLTFLoader would also drive descendant nodes' morph targets)`);
}

function pickAnimation(json, clips, spec) {
  if (spec === 'none') return null;
  const defs = json.animations || [];
  let index;
  if (/^\d+$/.test(spec)) {
    index = Number(spec);
    if (index >= defs.length) fail(`--animation ${spec}: the asset has ${defs.length} animation(s)`);
  } else {
    const hits = defs.map((a, i) => (a.name === spec ? i : -1)).filter((i) => i >= 0);
    if (hits.length === 0) {
      const names = defs.map((a, i) => `${i}: ${JSON.stringify(a.name ?? null)}`).join(', ');
      fail(`--animation ${JSON.stringify(spec)}: no animation of that name (the asset has ${names || 'none'})`);
    }
    if (hits.length > 1) fail(`--animation ${JSON.stringify(spec)}: ${hits.length} animations have that name (${hits.join(', ')}); give an index`);
    index = hits[0];
  }
  return { index, name: defs[index].name ?? null, clip: clips[index] };
}

async function main() {
  const args = parseArgs(process.argv.slice(2));
  const { THREE, GLTFLoader, version, url } = await importThree();
  const assetPath = path.resolve(args.asset);
  const { json, bin } = readAsset(assetPath);
  if (!json.asset || String(json.asset.version || '')[0] !== '2') fail(`${assetPath}: not a glTF 2.0 asset (asset.version ${JSON.stringify(json.asset && json.asset.version)})`);
  stripTextures(json);
  const assetDir = path.dirname(assetPath);

  const loader = new GLTFLoader();
  if ((json.extensionsUsed || []).includes('EXT_meshopt_compression')) {
    const { MeshoptDecoder } = await import(url('examples/jsm/libs/meshopt_decoder.module.js'));
    await MeshoptDecoder.ready;
    loader.setMeshoptDecoder(MeshoptDecoder);
  }
  // Buffers from disk: this parser's loadBuffer, replaced (a plugin callback sees the parser first).
  loader.register((parser) => {
    parser.loadBuffer = (index) => Promise.resolve().then(() => loadBufferBytes(parser.json, index, assetDir, bin));
    return { name: 'JAXPBR_node_buffers' };
  });
  const warnings = [];
  const warn = console.warn;
  console.warn = (...m) => warnings.push(m.join(' '));
  let gltf;
  try {
    gltf = await loader.parseAsync(json, assetDir + path.sep);
  } catch (e) {
    fail(`three's GLTFLoader could not load ${assetPath}: ${e && e.stack ? e.stack : e}`, 4);
  } finally {
    console.warn = warn;
  }
  const parser = gltf.parser;
  const sceneIndex = json.scene ?? 0;
  if (!gltf.scene) fail(`${assetPath}: the asset has no scene to pose`);
  const notes = warnings.map((w) => `three warned: ${w}`);
  const { found, skipped } = await primitiveObjects(parser, json, sceneIndex);
  zeroMissingMorphPositions(THREE, json, found, notes);

  const anim = pickAnimation(json, gltf.animations, args.animation);
  if (anim) await ownWeightsTracks(parser, json, anim.index, anim.clip, found, notes);
  const root = gltf.scene;
  let mixer = null;
  let action = null;
  if (anim) {
    mixer = new THREE.AnimationMixer(root);
    action = mixer.clipAction(anim.clip);
    action.setLoop(THREE.LoopOnce, 1);
    action.clampWhenFinished = true;
    action.play();
  }

  const bones = new Set();
  for (const { object } of found) if (object.isSkinnedMesh) for (const b of object.skeleton.bones) if (b) bones.add(b);

  const v = new THREE.Vector3();
  const results = found.map(({ node, mesh, primitive, object }) => ({
    node, mesh, primitive,
    kind: object.type,
    count: object.geometry.attributes.position.count,
    positions: [],
  }));
  for (const t of args.times) {
    if (mixer) {
      action.reset(); // un-pause after a time past the end (clampWhenFinished pauses the action)
      action.play();
      mixer.setTime(t);
    }
    root.updateMatrixWorld(true);
    // Joints outside the scene graph (allowed by glTF) get their world matrices too.
    for (const b of bones) b.updateWorldMatrix(true, false);
    found.forEach(({ object }, k) => {
      const n = object.geometry.attributes.position.count;
      const out = new Array(n);
      for (let i = 0; i < n; i++) {
        if (object.isMesh) object.getVertexPosition(i, v);
        else THREE.Mesh.prototype.getVertexPosition.call(object, i, v); // lines and points: morphs only
        v.applyMatrix4(object.matrixWorld);
        out[i] = [v.x, v.y, v.z];
      }
      results[k].positions.push(out);
    });
  }

  const doc = {
    three: version,
    asset: assetPath,
    scene: sceneIndex,
    animation: anim ? { index: anim.index, name: anim.name, duration: anim.clip.duration } : null,
    times: args.times,
    primitives: results,
    skipped,
    notes,
  };
  try {
    fs.writeFileSync(args.out, JSON.stringify(doc));
  } catch (e) {
    fail(`cannot write ${args.out}: ${e.message}`);
  }
}

main().catch((e) => fail(e && e.stack ? e.stack : String(e), 1));
