/* polarface offline viewer (docs/export.md, section "Viewer").
 *
 * Reads window.POLARFACE_VIEWER_DATA (viewer_data.js, written by polarface.report.viewer) and shows:
 *  - the exported glb in 3D (three.js r147 classic build, OrbitControls), its material or a colour-mapped
 *    parameter map (map selector), per dynamic frame the tracked mesh and textures (frame slider);
 *  - a 2D panel: the static result rendered by polarface at the first polarimetric camera as seen behind
 *    a linear analyzer at angle theta, I(theta) = (S0 + S1 cos 2theta + S2 sin 2theta) / 2.
 * Everything is inline (base64) so the page works from file:// without network, modules or fetch().
 * The page's state, and every error, is written as JSON into #status (read by the tests).
 */
(function () {
  'use strict';

  const status = { state: 'starting', errors: [] };
  const statusNode = document.getElementById('status');
  function report() {
    statusNode.textContent = JSON.stringify(status);
    document.title = 'polarface viewer: ' + status.state;
  }
  function fail(message) {
    status.errors.push(String(message));
    const box = document.getElementById('errors');
    box.textContent = status.errors.join('\n');
    box.hidden = false;
    report();
  }
  const consoleError = console.error.bind(console);
  console.error = function () {
    fail(Array.prototype.map.call(arguments, String).join(' '));
    consoleError.apply(null, arguments);
  };
  window.addEventListener('error', (event) => fail('error: ' + event.message));
  window.addEventListener('unhandledrejection', (event) => fail('unhandled rejection: ' + event.reason));
  report();

  const data = window.POLARFACE_VIEWER_DATA;
  if (!data) {
    fail('viewer_data.js did not load (POLARFACE_VIEWER_DATA missing)');
    return;
  }
  document.getElementById('source').textContent = data.title || '';

  // ---- decoding -------------------------------------------------------------------------------
  function base64Bytes(text) {
    const raw = atob(text);
    const bytes = new Uint8Array(raw.length);
    for (let i = 0; i < raw.length; i++) bytes[i] = raw.charCodeAt(i);
    return bytes;
  }
  function pngImage(base64) {
    const image = new Image();
    image.src = 'data:image/png;base64,' + base64;
    return image.decode().then(() => image);
  }
  function pixels(image) {
    const canvas = document.createElement('canvas');
    canvas.width = image.naturalWidth;
    canvas.height = image.naturalHeight;
    const context = canvas.getContext('2d', { willReadFrequently: true });
    context.drawImage(image, 0, 0);
    return context.getImageData(0, 0, canvas.width, canvas.height).data;
  }
  const textures = new Map();
  function texture(base64) {
    // Texture-space PNGs have row 0 at glTF v = 0, as the glb's own images: no flip.
    if (!textures.has(base64)) {
      textures.set(base64, pngImage(base64).then((image) => {
        const result = new THREE.Texture(image);
        result.flipY = false;
        result.encoding = THREE.sRGBEncoding;
        result.needsUpdate = true;
        return result;
      }));
    }
    return textures.get(base64);
  }

  // ---- 3D view ----------------------------------------------------------------------------------
  const view = document.getElementById('view');
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.outputEncoding = THREE.sRGBEncoding;
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  view.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.background = new THREE.Color(0x30343a);
  const camera = new THREE.PerspectiveCamera(30, 1, 0.001, 1000);
  scene.add(camera);
  scene.add(new THREE.HemisphereLight(0xffffff, 0x505050, 0.8));
  const headLight = new THREE.DirectionalLight(0xffffff, 1.0);
  headLight.position.set(0.3, 0.5, 1.0);
  camera.add(headLight);
  const controls = new THREE.OrbitControls(camera, renderer.domElement);
  controls.enableDamping = true;

  function resize() {
    const width = Math.max(view.clientWidth, 1);
    const height = Math.max(view.clientHeight, 1);
    renderer.setSize(width, height, false);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
  }
  window.addEventListener('resize', resize);

  const state = { face: null, material: null, unlit: null, staticPosition: null, staticNormal: null,
    mapName: 'material', frame: -1 };

  function frameView(object) {
    const box = new THREE.Box3().setFromObject(object);
    const centre = box.getCenter(new THREE.Vector3());
    const radius = Math.max(box.getSize(new THREE.Vector3()).length() / 2, 1e-6);
    // Look along the mean vertex normal (a face mesh's normals point mostly forward); glTF is +Y up.
    const direction = new THREE.Vector3(0, 0, 1);
    const normals = state.face.geometry.getAttribute('normal');
    if (normals) {
      const sum = new THREE.Vector3();
      for (let i = 0; i < normals.count; i++) sum.add(new THREE.Vector3().fromBufferAttribute(normals, i));
      sum.y = 0;
      if (sum.length() > 1e-9) direction.copy(sum.normalize());
    }
    const distance = radius / Math.sin(THREE.MathUtils.degToRad(camera.fov / 2)) * 1.05;
    camera.near = distance / 100;
    camera.far = distance * 100;
    camera.position.copy(centre).addScaledVector(direction, distance);
    camera.updateProjectionMatrix();
    controls.target.copy(centre);
    controls.update();
  }

  function currentFrame() {
    return state.frame >= 0 ? data.frames[state.frame] : null;
  }
  function mapTexture(name) {
    const frame = currentFrame();
    if (frame && frame.textures[name]) return texture(frame.textures[name]);
    const entry = data.maps.find((m) => m.name === name);
    return entry ? texture(entry.png) : Promise.resolve(null);
  }

  function showLegend(entry) {
    const legend = document.getElementById('legend');
    if (!entry || !entry.colorbar) {
      legend.hidden = true;
      return;
    }
    legend.hidden = false;
    document.getElementById('legend-bar').style.background =
      'linear-gradient(to right, ' + entry.colorbar.join(', ') + ')';
    document.getElementById('legend-min').textContent = entry.vmin.toPrecision(3);
    document.getElementById('legend-max').textContent = entry.vmax.toPrecision(3);
    document.getElementById('legend-label').textContent = entry.label;
  }

  function applyMaterial() {
    const name = state.mapName;
    if (name === 'material') {
      showLegend(null);
      state.face.material = state.material;
      const base = currentFrame() ? mapTexture(data.base_colour) : Promise.resolve(state.materialMap);
      return base.then((map) => {
        state.material.map = map;
        state.material.needsUpdate = true;
      });
    }
    showLegend(data.maps.find((m) => m.name === name));
    return mapTexture(name).then((map) => {
      state.unlit.map = map;
      state.unlit.needsUpdate = true;
      state.face.material = state.unlit;
    });
  }

  function applyFrame() {
    const geometry = state.face.geometry;
    const frame = currentFrame();
    const label = document.getElementById('frame-label');
    if (!frame) {
      geometry.setAttribute('position', state.staticPosition);
      if (state.staticNormal) geometry.setAttribute('normal', state.staticNormal);
      label.textContent = 'static result';
    } else {
      const positions = new Float32Array(base64Bytes(frame.positions).buffer);
      const normals = new Int8Array(base64Bytes(frame.normals).buffer);
      if (positions.length !== state.staticPosition.count * 3) {
        fail('frame ' + frame.index + ': ' + positions.length / 3 + ' positions for ' +
          state.staticPosition.count + ' glb vertices');
        return Promise.resolve();
      }
      geometry.setAttribute('position', new THREE.BufferAttribute(positions, 3));
      geometry.setAttribute('normal', new THREE.BufferAttribute(normals, 3, true));
      label.textContent = 'frame ' + frame.index + ' (' + frame.time_s.toFixed(3) + ' s)';
    }
    geometry.computeBoundingSphere();
    geometry.computeBoundingBox();
    return applyMaterial();
  }

  function buildControls() {
    const select = document.getElementById('map');
    const option = (value, text) => {
      const node = document.createElement('option');
      node.value = value;
      node.textContent = text;
      select.appendChild(node);
    };
    option('material', 'glb material (lit)');
    for (const entry of data.maps) option(entry.name, entry.label);
    select.addEventListener('change', () => {
      state.mapName = select.value;
      applyMaterial();
    });
    const slider = document.getElementById('frame');
    slider.max = String(data.frames.length);
    slider.disabled = data.frames.length === 0;
    slider.addEventListener('input', () => {
      state.frame = Number(slider.value) - 1;
      applyFrame();
    });
  }

  function loadGlb() {
    return new Promise((resolve, reject) => {
      const bytes = base64Bytes(data.glb);
      new THREE.GLTFLoader().parse(bytes.buffer, '', resolve, reject);
    }).then((gltf) => {
      const meshes = [];
      gltf.scene.traverse((node) => { if (node.isMesh) meshes.push(node); });
      if (meshes.length === 0) throw new Error('the glb holds no mesh');
      scene.add(gltf.scene);
      const face = meshes[0];
      state.face = face;
      state.material = face.material;
      state.material.side = THREE.DoubleSide;
      state.materialMap = face.material.map || null;
      state.unlit = new THREE.MeshBasicMaterial({ side: THREE.DoubleSide });
      state.staticPosition = face.geometry.getAttribute('position');
      state.staticNormal = face.geometry.getAttribute('normal') || null;
      status.meshes = meshes.length;
      status.vertices = state.staticPosition.count;
      status.material_map = Boolean(state.materialMap);
      frameView(gltf.scene);
    });
  }

  // ---- polarizer panel --------------------------------------------------------------------------
  const polar = { width: 0, height: 0, s: null, mask: null, context: null, image: null };

  function decodeStokes(stokes) {
    const names = ['s0', 's1', 's2', 'mask'];
    return Promise.all(names.map((n) => pngImage(stokes[n]))).then((images) => {
      const [b0, b1, b2, bm] = images.map(pixels);
      const count = stokes.width * stokes.height;
      const s = [new Float32Array(count * 3), new Float32Array(count * 3), new Float32Array(count * 3)];
      const mask = new Uint8Array(count);
      const x = stokes.scale;
      for (let p = 0; p < count; p++) {
        mask[p] = bm[4 * p] > 127 ? 1 : 0;
        for (let c = 0; c < 3; c++) {
          const u = b0[4 * p + c] / 255;
          s[0][3 * p + c] = x * u * u;
          const t1 = 2 * b1[4 * p + c] / 255 - 1;
          const t2 = 2 * b2[4 * p + c] / 255 - 1;
          s[1][3 * p + c] = x * Math.sign(t1) * t1 * t1;
          s[2][3 * p + c] = x * Math.sign(t2) * t2 * t2;
        }
      }
      Object.assign(polar, { width: stokes.width, height: stokes.height, s, mask });
      const canvas = document.getElementById('polarizer');
      canvas.width = stokes.width;
      canvas.height = stokes.height;
      polar.context = canvas.getContext('2d');
      polar.image = polar.context.createImageData(stokes.width, stokes.height);
    });
  }

  function analyzerMean(thetaDeg) {
    // Mean linear RGB of I(theta) = (S0 + S1 cos 2theta + S2 sin 2theta) / 2 over the rendered face.
    const t = 2 * THREE.MathUtils.degToRad(thetaDeg);
    const c = Math.cos(t), s = Math.sin(t);
    const sum = [0, 0, 0];
    let n = 0;
    for (let p = 0; p < polar.mask.length; p++) {
      if (!polar.mask[p]) continue;
      n++;
      for (let k = 0; k < 3; k++) {
        const i = 3 * p + k;
        sum[k] += 0.5 * (polar.s[0][i] + polar.s[1][i] * c + polar.s[2][i] * s);
      }
    }
    return sum.map((v) => v / Math.max(n, 1));
  }

  function srgb(linear) {
    const x = Math.min(Math.max(linear, 0), 1);
    return x <= 0.0031308 ? 12.92 * x : 1.055 * Math.pow(x, 1 / 2.4) - 0.055;
  }

  function drawPolarizer(thetaDeg) {
    const t = 2 * THREE.MathUtils.degToRad(thetaDeg);
    const c = Math.cos(t), s = Math.sin(t);
    const gain = data.stokes.exposure;  // display: exposure * 2 I(theta), sRGB encoded
    const out = polar.image.data;
    for (let p = 0; p < polar.mask.length; p++) {
      for (let k = 0; k < 3; k++) {
        const i = 3 * p + k;
        const value = gain * (polar.s[0][i] + polar.s[1][i] * c + polar.s[2][i] * s);
        out[4 * p + k] = polar.mask[p] ? Math.round(255 * srgb(value)) : 24;
      }
      out[4 * p + 3] = 255;
    }
    polar.context.putImageData(polar.image, 0, 0);
    document.getElementById('theta-label').textContent = thetaDeg + '\u00b0';
  }

  function setupPolarizer() {
    const slider = document.getElementById('theta');
    if (!data.stokes) {
      slider.disabled = true;
      document.getElementById('polarizer-caption').textContent = 'no Stokes render in this export';
      return Promise.resolve();
    }
    return decodeStokes(data.stokes).then(() => {
      status.polarizer_means = {};
      for (const angle of [0, 45, 90, 135]) status.polarizer_means[angle] = analyzerMean(angle);
      slider.addEventListener('input', () => drawPolarizer(Number(slider.value)));
      drawPolarizer(Number(slider.value));
      document.getElementById('polarizer-caption').textContent = 'camera ' + data.stokes.camera +
        ': the static result rendered by polarface behind a linear analyzer at \u03b8 from image x';
    });
  }

  function applyLocationHash() {
    // index.html#map=c_h_out&frame=2&theta=45 opens the page with these settings (links, tests).
    const wanted = new URLSearchParams(window.location.hash.replace(/^#/, ''));
    const select = document.getElementById('map');
    if (wanted.has('map')) {
      if (!['material', ...data.maps.map((m) => m.name)].includes(wanted.get('map'))) {
        fail('unknown map "' + wanted.get('map') + '" in the page address');
      } else {
        select.value = wanted.get('map');
        state.mapName = select.value;
      }
    }
    if (wanted.has('frame')) {
      const slider = document.getElementById('frame');
      slider.value = wanted.get('frame');
      state.frame = Number(slider.value) - 1;
    }
    if (wanted.has('theta') && data.stokes) {
      const slider = document.getElementById('theta');
      slider.value = wanted.get('theta');
      drawPolarizer(Number(slider.value));
    }
  }

  // ---- start ------------------------------------------------------------------------------------
  function animate() {
    requestAnimationFrame(animate);
    controls.update();
    renderer.render(scene, camera);
  }

  status.state = 'loading';
  report();
  resize();
  buildControls();
  Promise.all([loadGlb(), setupPolarizer()])
    .then(() => applyLocationHash())
    .then(() => applyFrame())
    .then(() => {
      status.state = 'ready';
      status.shown = { map: state.mapName, frame: currentFrame() ? currentFrame().index : null,
        theta: Number(document.getElementById('theta').value) };
      status.maps = data.maps.map((m) => m.name);
      status.frames = data.frames.length;
      status.controls = ['map', 'frame', 'theta'].filter((id) => document.getElementById(id));
      report();
      animate();
    })
    .catch((error) => fail('loading failed: ' + (error && error.stack ? error.stack : error)));
}());
