// flowmocap view: the input with the fitted body over it, and the body in 3D in the world
// frame (floor at y = 0). Served by `flowmocap view RESULT` (flowmocap/commands/view.py):
//   /api/meta.json  fps, frames, image size, the camera (OpenGL matrices, world frame), floor
//   /motion.glb     the skinned, animated body (the same file `flowmocap export --format glb` writes);
//                   with several people (a `track --person all` folder) /motion/N.glb is person N's,
//                   all in the ground frame of the person whose floor is shared, meta.floor_of
//                   (meta.people: glb, colour, rows, path)
//   /frame/K.jpg    input frame of page frame K (a result row; with several people, an input
//                   frame any of them was tracked in)
// URL parameters: ?frame=K (start at row K, paused), ?play=1 (start playing), ?scale=S (draw
// the input at S x its size instead of fitting it into its pane), ?az=DEG (the 3D view's
// start, turned DEG about the vertical from the video camera's side; default 30).
// When a frame is drawn, <body> carries data-frame=K, data-ready=1, data-overlay=[left,
// top, width, height] (the overlay's place on the page, CSS pixels), data-people (one 0/1
// per person: drawn in this frame or not), data-feet (two 0/1 per person, left and right:
// a disc under that foot, standing) and, where the result has
// the 3D sources' disagreement, data-review=0/1 (the frame is among the run's most uncertain
// tenth, for anyone) and data-review-people (one 0/1 per person), for tests. The strip under
// the slider marks those frames in red; the label names whose. data-unseen: per person, comma
// separated, "held" / "between" / "flow" where they were tracked without being seen (the label says so), "-"
// elsewhere; the strip marks those frames in grey.
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';

const $ = (id) => document.getElementById(id);
const label = $('label');

function fail(msg) {
  label.textContent = 'error: ' + msg;
  document.title = 'flowmocap view: error: ' + msg;
  document.body.dataset.error = msg;
}
window.addEventListener('error', (e) => fail(String(e.message)));
window.addEventListener('unhandledrejection', (e) => fail(String(e.reason)));

const params = new URLSearchParams(location.search);
const meta = await (await fetch('/api/meta.json')).json();
const T = meta.num_frames;
const fps = meta.fps;
$('slider').max = String(T - 1);
const many = meta.people.length > 1;
const hex = (c) => '#' + c.map((v) => Math.round(255 * v).toString(16).padStart(2, '0')).join('');
$('info').textContent = `${meta.name}: ${T} frames at ${fps} fps, floor: ${meta.floor}` +
  (meta.smoothed ? ', smoothed' : '') + (meta.has_input ? '' : ' (input not found: grey frames)');
if (many) {  // a key of the people in their colours
  $('info').append(', people: ');
  meta.people.forEach((p, i) => {
    const tag = document.createElement('span');
    tag.textContent = p.name + (i < meta.people.length - 1 ? ' ' : '');
    tag.style.color = hex(p.colour);
    $('info').append(tag);
  });
}

// one scene, seen by two renderers: the result's camera (over the image) and an orbit camera
const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 2.2));
const sun = new THREE.DirectionalLight(0xffffff, 1.6);
sun.position.set(2, 4, 3);
scene.add(sun);
const HELPERS = 1;  // layer of things only the 3D view shows
const grid = new THREE.GridHelper(20, 20, 0xb0b8c4, 0x5c6470);
grid.layers.set(HELPERS);
scene.add(grid);
const floor = new THREE.Mesh(new THREE.PlaneGeometry(20, 20).rotateX(-Math.PI / 2),
  new THREE.MeshBasicMaterial({ color: 0x2c3038, transparent: true, opacity: 0.6, depthWrite: false }));
floor.position.y = -0.001;
floor.layers.set(HELPERS);
scene.add(floor);

// one skinned body per person, each with its own animation clock (its result's rows)
const bodies = [];
for (const p of meta.people) {
  const gltf = await new GLTFLoader().loadAsync(p.glb);
  const body = gltf.scene;
  body.traverse((o) => {
    if (!o.isMesh) return;
    o.frustumCulled = false;
    if (p.colour) { o.material = o.material.clone(); o.material.color.setRGB(...p.colour); }
  });
  scene.add(body);
  const mixer = new THREE.AnimationMixer(body);
  mixer.clipAction(gltf.animations[0]).play();
  bodies.push({ body, mixer, rows: p.rows });
}

// the result's camera: world-to-camera as OpenGL matrices computed by the server (where the camera
// turned during the clip, meta.gl_cameras has each frame's, and the 3D view's pyramid turns with it)
const videoCam = new THREE.PerspectiveCamera();
videoCam.matrixAutoUpdate = false;
videoCam.matrix.fromArray(meta.gl_camera.matrix_world);
videoCam.updateMatrixWorld(true);
videoCam.projectionMatrix.fromArray(meta.gl_camera.projection);
videoCam.projectionMatrixInverse.copy(videoCam.projectionMatrix).invert();
videoCam.layers.set(0);

// the camera in the 3D view: a pyramid from its centre to the image corners at 0.6 m
let cameraPyramid = null;
const firstCamInverse = videoCam.matrixWorld.clone().invert();
{
  const c = new THREE.Vector3().setFromMatrixPosition(videoCam.matrixWorld);
  const pts = [];
  const corners = meta.gl_camera.corners;  // 4 world points
  for (const p of corners) pts.push(c.x, c.y, c.z, p[0], p[1], p[2]);
  for (let i = 0; i < 4; i++) {
    const a = corners[i], b = corners[(i + 1) % 4];
    pts.push(a[0], a[1], a[2], b[0], b[1], b[2]);
  }
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.Float32BufferAttribute(pts, 3));
  const pyramid = new THREE.LineSegments(g, new THREE.LineBasicMaterial({ color: 0xffb040 }));
  pyramid.layers.set(HELPERS);
  pyramid.matrixAutoUpdate = false;  // where the camera turns, moved with it (draw())
  scene.add(pyramid);
  cameraPyramid = pyramid;
}

// each pelvis's path dropped onto the floor (in the person's colour with several), and a
// disc under each foot of every person while it stands (left green, right red)
for (const person of meta.people) {
  const pts = person.path.filter((q) => q !== null).flatMap((q) => [q[0], 0.003, q[2]]);
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.Float32BufferAttribute(pts, 3));
  const colour = person.colour ? new THREE.Color(...person.colour) : new THREE.Color(0x50a0ff);
  const path = new THREE.Line(g, new THREE.LineBasicMaterial({ color: colour }));
  path.layers.set(HELPERS);
  scene.add(path);
}
const discs = meta.people.map(() => [0, 1].map((side) => {
  const d = new THREE.Mesh(new THREE.CircleGeometry(0.07, 24).rotateX(-Math.PI / 2),
    new THREE.MeshBasicMaterial({ color: side ? 0xff6060 : 0x60d060 }));
  d.layers.set(HELPERS);
  scene.add(d);
  return d;
}));

const overlayR = new THREE.WebGLRenderer({ canvas: $('overlay'), alpha: true, antialias: true,
  preserveDrawingBuffer: true });
overlayR.setPixelRatio(1);
overlayR.setSize(meta.width, meta.height, false);
overlayR.setClearColor(0x000000, 0);
const worldR = new THREE.WebGLRenderer({ canvas: $('world'), antialias: true, preserveDrawingBuffer: true });
worldR.setPixelRatio(window.devicePixelRatio);
worldR.setClearColor(0x1c1e22, 1);

const orbitCam = new THREE.PerspectiveCamera(45, 1, 0.05, 200);
orbitCam.layers.enable(HELPERS);
const centre = new THREE.Vector3(...meta.centre);
{  // start beside the video camera, turned 40 degrees about the vertical, so both show
  const cam = new THREE.Vector3().setFromMatrixPosition(videoCam.matrixWorld);
  const away = cam.clone().sub(centre).setY(0);
  if (away.length() < 1e-6) away.set(0, 0, 1);
  away.setLength(Math.min(Math.max(away.length() * 1.35, 3.5), 10.0));
  away.applyAxisAngle(new THREE.Vector3(0, 1, 0), THREE.MathUtils.degToRad(Number(params.get('az') ?? 30)));
  orbitCam.position.copy(centre).add(away).add(new THREE.Vector3(0, 0.45 * away.length(), 0));
}
const controls = new OrbitControls(orbitCam, $('world'));
controls.target.copy(centre);
controls.update();
document.body.dataset.orbit = JSON.stringify(orbitCam.position.toArray().map((v) => +v.toFixed(3)));
controls.addEventListener('change', () => worldR.render(scene, orbitCam));

function layout() {
  const pane = $('video-pane').getBoundingClientRect();
  const s = Number(params.get('scale')) || Math.min(pane.width / meta.width, pane.height / meta.height);
  const box = $('overlay-box');
  box.style.width = `${meta.width * s}px`;
  box.style.height = `${meta.height * s}px`;
  const r = box.getBoundingClientRect();
  document.body.dataset.overlay = JSON.stringify([r.left, r.top, r.width, r.height]);
  const w = $('world-pane').getBoundingClientRect();
  worldR.setSize(w.width, w.height, false);
  orbitCam.aspect = w.width / Math.max(w.height, 1);
  orbitCam.updateProjectionMatrix();
}
window.addEventListener('resize', () => { layout(); draw(); });

// the frames to review (the 3D sources part most): red marks on a strip under the slider
function drawStrip() {
  const strip = $('strip');
  const unseenAt = (k) => meta.people.some((person) => person.unseen && person.unseen[k]);
  let anyUnseen = false;
  for (let k = 0; k < T && !anyUnseen; k++) anyUnseen = unseenAt(k);
  if (!meta.review && !anyUnseen) { strip.style.display = 'none'; return; }
  const w = Math.max(1, Math.round($('slider').getBoundingClientRect().width));
  strip.width = w;
  const g = strip.getContext('2d');
  g.fillStyle = '#3a404a';
  g.fillRect(0, 0, w, strip.height);
  for (let k = 0; k < T; k++) {
    const x = Math.floor((k / Math.max(T - 1, 1)) * (w - 2));
    if (meta.review && meta.review[k]) { g.fillStyle = '#ff5050'; g.fillRect(x, 0, 2, strip.height); }
    else if (unseenAt(k)) { g.fillStyle = '#9aa0aa'; g.fillRect(x, 0, 2, strip.height); }
  }
}
window.addEventListener('resize', drawStrip);

let current = 0;
let playing = false;
let token = 0;

function draw() {
  if (meta.gl_cameras) {  // the camera turned during the clip: this frame's camera, and its pyramid
    videoCam.matrix.fromArray(meta.gl_cameras[current]);
    videoCam.updateMatrixWorld(true);
    cameraPyramid.matrix.copy(videoCam.matrixWorld).multiply(firstCamInverse);
    cameraPyramid.matrixWorldNeedsUpdate = true;
  }
  if (meta.gl_projections) {  // the camera zoomed during the clip: this frame's focal length
    videoCam.projectionMatrix.fromArray(meta.gl_projections[current]);
    videoCam.projectionMatrixInverse.copy(videoCam.projectionMatrix).invert();
  }
  const r = $('overlay-box').getBoundingClientRect();
  document.body.dataset.overlay = JSON.stringify([r.left, r.top, r.width, r.height]);
  const shown = [];
  for (const b of bodies) {
    const row = b.rows[current];
    b.body.visible = row >= 0;  // a person not tracked in this frame is not drawn
    if (row >= 0) { b.mixer.setTime(row / fps); b.body.updateMatrixWorld(true); shown.push(1); } else shown.push(0);
  }
  document.body.dataset.people = shown.join('');
  const standing = [];
  meta.people.forEach((person, k) => {
    for (const side of [0, 1]) {
      const f = person.feet[current] && person.feet[current][side];
      discs[k][side].visible = !!f && person.contacts[current][side] === 1;
      // on the floor for the person whose floor it is; where the foot stands for the others (a box, a step)
      if (f) discs[k][side].position.set(f[0], k === (meta.floor_of || 0) ? 0.004 : f[1] + 0.004, f[2]);
      standing.push(discs[k][side].visible ? 1 : 0);
    }
  });
  document.body.dataset.feet = standing.join('');  // per person, left then right: a disc shown
  overlayR.render(scene, videoCam);
  worldR.render(scene, orbitCam);
}

async function setFrame(k) {
  current = Math.max(0, Math.min(T - 1, Math.round(Number.isFinite(k) ? k : 0)));  // ?frame=abc: the first
  const mine = ++token;
  $('slider').value = String(current);
  // the time in the input video (a result may start at a later frame)
  const seconds = meta.times ? meta.times[current] : meta.frame_index[current] / fps;  // a variable-rate video's own
  label.textContent = `frame ${meta.frame_index[current]} (${current + 1}/${T}) ${seconds.toFixed(2)} s`;
  // who was not seen in this frame: held at the last seen pose, or tracked by flow alone
  const unseen = meta.people.map((person) => (person.unseen ? person.unseen[current] : ''));
  unseen.forEach((how, k) => {
    const words = { held: 'held at the last seen pose', between: 'filled in between the poses before and after',
      flow: 'tracked by flow alone' };
    if (how) label.textContent += `, ${many ? meta.people[k].name + ' ' : ''}not seen (${words[how] || how})`;
  });
  document.body.dataset.unseen = unseen.map((how) => how || '-').join(',');
  if (meta.review) {
    // each person's: "3D sources part 4.2 cm (review)"; with several people, named
    const parts = meta.people.map((person) => {
      const d = person.disagreement_cm ? person.disagreement_cm[current] : null;
      if (d === null || d === undefined) return null;
      return (many ? `${person.name}: ` : '') + `3D sources part ${d.toFixed(1)} cm` +
        (person.review[current] ? ' (review)' : '');
    }).filter((x) => x !== null);
    if (parts.length) label.textContent += ', ' + parts.join(', ');
    label.classList.toggle('review', meta.review[current] === 1);
    document.body.dataset.review = String(meta.review[current]);
    // per person, 0/1: that person's frame is to be reviewed
    document.body.dataset.reviewPeople = meta.people.map((person) => (person.review ? person.review[current] : 0)).join('');
  }
  label.title = label.textContent;  // the whole text where a narrow window cuts it
  const img = $('frame');
  const loaded = await new Promise((resolve) => {
    img.onload = () => resolve(true); img.onerror = () => resolve(false); img.src = `/frame/${current}.jpg`;
  });
  $('frame-caption').textContent = loaded ? 'input with the fitted body (the result\'s camera)'
    : `input frame ${meta.frame_index[current]} could not be loaded: is flowmocap view still running?`;
  if (mine !== token) return;  // a newer frame was asked for meanwhile
  draw();
  document.body.dataset.frame = String(current);
  document.body.dataset.slider = String(Math.round($('slider').getBoundingClientRect().width));  // px, for tests
  document.body.dataset.ready = '1';
  document.title = `flowmocap view: frame ${current}`;
}

function setPlaying(on) {
  playing = on;
  $('play').innerHTML = on ? '&#10074;&#10074;' : '&#9654;';
  if (on) {
    const t0 = performance.now() - (current / fps) * 1000;
    const tick = async () => {
      if (!playing) return;
      const k = Math.floor(((performance.now() - t0) / 1000) * fps) % T;
      if (k !== current) await setFrame(k);
      requestAnimationFrame(tick);
    };
    requestAnimationFrame(tick);
  }
}

$('play').addEventListener('click', () => setPlaying(!playing));
$('prev').addEventListener('click', () => { setPlaying(false); setFrame(current - 1); });
$('next').addEventListener('click', () => { setPlaying(false); setFrame(current + 1); });
$('slider').addEventListener('input', (e) => { setPlaying(false); setFrame(Number(e.target.value)); });
window.addEventListener('keydown', (e) => {
  // preventDefault: a focused slider would step once more by itself
  if (e.key === ' ') { setPlaying(!playing); e.preventDefault(); }
  if (e.key === 'ArrowLeft') { setPlaying(false); setFrame(current - 1); e.preventDefault(); }
  if (e.key === 'ArrowRight') { setPlaying(false); setFrame(current + 1); e.preventDefault(); }
});

layout();
drawStrip();
await setFrame(Number(params.get('frame') || 0));  // setFrame takes a non-number as the first frame
if (params.get('play') === '1') setPlaying(true);
