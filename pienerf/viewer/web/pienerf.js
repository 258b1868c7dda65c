// The demo page's script: runs meshcat's own Viewer, feeds it the server's msgpack commands, and sends the user's
// pointer rays, camera and control changes back as JSON messages. Rays and the camera travel in the scene's
// y-up coordinates: the inverse of the root node "/pienerf" (which turns y-up into meshcat's z-up world).
"use strict";

(function () {
  const THREE = MeshCat.THREE;
  const viewer = new MeshCat.Viewer(document.getElementById("meshcat-pane"));
  const canvas = viewer.renderer.domElement;
  const raycaster = new THREE.Raycaster();
  const element = (id) => document.getElementById(id);
  const stats = {
    frames: 0, rafPerSecond: 0, renders: 0, rendersPerSecond: 0, updates: 0, updatesPerSecond: 0,
    updateMilliseconds: 0, nerfImages: 0, messages: 0, mode: null, controls: null, lastMessage: "", open: false,
  };
  window.pienerf = { viewer, stats };

  // -- the connection ------------------------------------------------------------------------------------

  const socket = new WebSocket(`ws://${location.host}/ws`);
  socket.binaryType = "arraybuffer";
  viewer.connection = socket;
  socket.onopen = () => { stats.open = true; };
  socket.onclose = () => { stats.open = false; element("status").textContent = "disconnected: reload the page"; };
  socket.onmessage = (event) => {
    if (typeof event.data === "string") {
      onProjectMessage(JSON.parse(event.data));
    } else {
      viewer.handle_command_message(event);
    }
  };
  function send(message) {
    if (socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message));
  }

  // meshcat's commands go to meshcat; "set_vertices" replaces a geometry's position buffer in place.
  const meshcatCommand = viewer.handle_command.bind(viewer);
  viewer.handle_command = (command) => {
    if (command.type === "set_vertices") setVertices(command.path, command.positions);
    else if (command.type === "set_colors") setColors(command.path, command.colors);
    else meshcatCommand(command);
  };
  const meshcatRender = viewer.render.bind(viewer);
  viewer.render = () => { stats.renders += 1; meshcatRender(); };

  function objectAt(path) {
    const names = path.split("/").filter((name) => name.length > 0);
    return viewer.scene_tree.find(names.concat(["<object>"])).object;
  }

  function setVertices(path, values) {
    const start = performance.now();
    const object = objectAt(path);
    const geometry = object.geometry;
    const position = geometry && geometry.attributes ? geometry.attributes.position : undefined;
    if (position === undefined || !(values instanceof Float32Array) || values.length !== position.array.length) return;
    position.array.set(values);
    position.needsUpdate = true;
    if (object.isMesh) geometry.computeVertexNormals();
    geometry.boundingSphere = null; // picking recomputes them
    geometry.boundingBox = null;
    stats.updates += 1;
    stats.updateMilliseconds += (performance.now() - start - stats.updateMilliseconds) / stats.updates; // mean
    viewer.set_dirty();
  }

  function setColors(path, values) {
    const geometry = objectAt(path).geometry;
    const color = geometry && geometry.attributes ? geometry.attributes.color : undefined;
    if (color === undefined || !(values instanceof Float32Array) || values.length !== color.array.length) return;
    color.array.set(values);
    color.needsUpdate = true;
    stats.colorUpdates = (stats.colorUpdates || 0) + 1;
    viewer.set_dirty();
  }

  // -- scene coordinates ---------------------------------------------------------------------------------

  function worldToScene() {
    const root = viewer.scene_tree.find(["pienerf"]).object;
    root.updateMatrixWorld(true);
    return new THREE.Matrix4().copy(root.matrixWorld).invert();
  }

  function pointerRay(event) {
    const rect = canvas.getBoundingClientRect();
    const ndc = new THREE.Vector2(
      ((event.clientX - rect.left) / rect.width) * 2 - 1,
      -((event.clientY - rect.top) / rect.height) * 2 + 1,
    );
    viewer.camera.updateMatrixWorld();
    raycaster.setFromCamera(ndc, viewer.camera);
    return raycaster.ray;
  }

  function rayMessage(type, ray) {
    const toScene = worldToScene();
    return {
      type,
      origin: ray.origin.clone().applyMatrix4(toScene).toArray(),
      direction: ray.direction.clone().transformDirection(toScene).toArray(),
    };
  }

  // -- pointer: a press on the body picks it, moving drags it, letting go after a move releases ------------

  let press = null;
  canvas.addEventListener("pointerdown", (event) => {
    if (event.button !== 0) return;
    const ray = pointerRay(event);
    const body = objectAt("/pienerf/body");
    if (!body.isMesh || raycaster.intersectObject(body, false).length === 0) return; // the orbit controls take it
    event.stopPropagation();
    event.preventDefault();
    canvas.setPointerCapture(event.pointerId);
    press = { x: event.clientX, y: event.clientY, moved: false };
    send(rayMessage("pick", ray));
  });
  canvas.addEventListener("pointermove", (event) => {
    if (press === null) return;
    event.stopPropagation();
    if (Math.hypot(event.clientX - press.x, event.clientY - press.y) > 3) press.moved = true;
    if (press.moved) send(rayMessage("drag", pointerRay(event)));
  });
  function endPress(event) {
    if (press === null) return;
    event.stopPropagation();
    if (press.moved) send({ type: "release" }); // a click keeps the point picked for pin / push / cut
    press = null;
  }
  canvas.addEventListener("pointerup", endPress);
  canvas.addEventListener("pointercancel", endPress);

  // -- the camera, sent when it changes (the NeRF mode renders from it) -----------------------------------

  let sentView = "";
  let lastViewTime = 0;
  function sendCamera(now) {
    const camera = viewer.camera;
    if (!camera || !camera.isPerspectiveCamera || now - lastViewTime < 100) return;
    camera.updateMatrixWorld();
    const matrix = worldToScene().multiply(camera.matrixWorld).toArray();
    const fov = (2 * Math.atan(Math.tan((camera.fov * Math.PI) / 360) / camera.zoom) * 180) / Math.PI;
    const aspect = canvas.clientWidth / Math.max(1, canvas.clientHeight);
    const view = JSON.stringify([matrix.map((v) => v.toFixed(5)), fov.toFixed(4), aspect.toFixed(4)]);
    if (view === sentView || socket.readyState !== WebSocket.OPEN) return;
    sentView = view;
    lastViewTime = now;
    send({ type: "camera", matrix, fov, aspect });
  }

  // -- the page's own frame rate --------------------------------------------------------------------------

  let second = performance.now();
  let counted = { frames: 0, renders: 0, updates: 0 };
  function tick(now) {
    stats.frames += 1;
    sendCamera(now);
    if (now - second >= 1000) {
      const scale = 1000 / (now - second);
      stats.rafPerSecond = (stats.frames - counted.frames) * scale;
      stats.rendersPerSecond = (stats.renders - counted.renders) * scale;
      stats.updatesPerSecond = (stats.updates - counted.updates) * scale;
      counted = { frames: stats.frames, renders: stats.renders, updates: stats.updates };
      second = now;
      element("page-rate").textContent = `page: ${stats.rafPerSecond.toFixed(0)} frames/s, ` +
        `${stats.rendersPerSecond.toFixed(0)} renders/s, ${stats.updatesPerSecond.toFixed(0)} body updates/s`;
    }
    requestAnimationFrame(tick);
  }
  requestAnimationFrame(tick);

  // -- the project's messages -----------------------------------------------------------------------------

  const nerf = element("nerf");
  function onProjectMessage(message) {
    stats.messages += 1;
    switch (message.type) {
      case "controls": showControls(message); break;
      case "status":
        element("status").textContent = message.text;
        element("breakdown").textContent = message.breakdown;
        element("contact").textContent = message.contact || "";
        break;
      case "message":
        stats.lastMessage = message.text;
        element("message").textContent = message.text;
        break;
      case "progress":
        element("progress-row").hidden = message.fraction === null;
        if (message.fraction !== null) element("progress").value = message.fraction;
        element("stage").textContent = message.stage;
        break;
      case "view":
        viewer.camera.position.fromArray(message.position);
        viewer.controls.target.fromArray(message.target);
        viewer.controls.update();
        viewer.set_dirty();
        break;
      case "mode":
        stats.mode = message.mode;
        nerf.hidden = message.mode !== "nerf";
        viewer.set_dirty();
        break;
      case "nerf":
        nerf.src = message.image;
        stats.nerfImages += 1;
        break;
      default:
        console.warn("unknown message from the server", message.type);
    }
  }

  // -- controls -------------------------------------------------------------------------------------------

  function si(value, unit) {
    for (const [factor, prefix] of [[1e9, "G"], [1e6, "M"], [1e3, "k"]]) {
      if (Math.abs(value) >= factor) return `${+(value / factor).toPrecision(3)} ${prefix}${unit}`;
    }
    return `${+value.toPrecision(3)} ${unit}`;
  }
  const sliders = {
    young_modulus: { toValue: (s) => 10 ** s, toSlider: (v) => Math.log10(v), text: (v) => si(v, "Pa") },
    poisson_ratio: { text: (v) => v.toFixed(2) },
    density: { text: (v) => `${v.toFixed(0)} kg/m³` },
    damping: { text: (v) => `${v.toFixed(1)} 1/s` },
    gravity: { text: (v) => `${v.toFixed(1)} m/s²` },
    kernel_count: { text: (v) => `${v.toFixed(0)}`, local: true },
  };
  for (const [name, slider] of Object.entries(sliders)) {
    const input = element(name);
    const value = () => (slider.toValue ? slider.toValue(+input.value) : +input.value);
    input.addEventListener("input", () => { element(`${name}-value`).textContent = slider.text(value()); });
    if (!slider.local) input.addEventListener("change", () => send({ type: "set", name, value: value() }));
  }
  // a garment scene's sliders: κ on a log scale
  const garmentSliders = {
    fabric_density: { text: (v) => `${v.toFixed(0)} kg/m³` },
    kappa_s: { toValue: (s) => 10 ** s, toSlider: (v) => Math.log10(v), text: (v) => v.toPrecision(2) },
    kappa_b: { toValue: (s) => 10 ** s, toSlider: (v) => Math.log10(v), text: (v) => v.toPrecision(2) },
    friction: { text: (v) => v.toFixed(2) },
    speed: { text: (v) => `${v.toFixed(2)}×` },
    frame: { text: (v) => `${v.toFixed(0)}` },
  };
  for (const [name, slider] of Object.entries(garmentSliders)) {
    const input = element(name);
    const value = () => (slider.toValue ? slider.toValue(+input.value) : +input.value);
    input.addEventListener("input", () => { element(`${name}-value`).textContent = slider.text(value()); });
    input.addEventListener("change", () => send({ type: "set", name, value: value() }));
  }
  for (const name of ["motion", "preset"]) {
    element(name).addEventListener("change", (event) => send({ type: "set", name, value: event.target.value }));
  }
  element("scene").addEventListener("change", (event) => send({ type: "scene", name: event.target.value }));
  for (const name of ["model", "render_mode"]) {
    element(name).addEventListener("change", (event) => send({ type: "set", name, value: event.target.value }));
  }
  element("resample").addEventListener("click", () => send({ type: "resample", kernel_count: +element("kernel_count").value }));

  // -- the panel: its controls fold away, and start folded in a small window, so that the body stays in view ----

  const panel = element("panel");
  function setCollapsed(collapsed) {
    panel.classList.toggle("collapsed", collapsed);
    element("collapse").textContent = collapsed ? "show controls" : "hide controls";
  }
  element("collapse").addEventListener("click", () => setCollapsed(!panel.classList.contains("collapsed")));
  setCollapsed(window.innerWidth < 800);
  for (const name of ["pin", "push", "cut", "release", "reset", "play", "pause"]) {
    element(name).addEventListener("click", () => send({ type: name }));
  }

  function fillSelect(select, options, value) {
    if ([...select.options].map((o) => o.value).join() !== options.join()) {
      select.replaceChildren(...options.map((option) => new Option(option, option)));
    }
    select.value = value;
  }

  function showControls(controls) {
    stats.controls = controls;
    const scenes = controls.scenes || [];
    element("scene-panel").hidden = scenes.length < 2;
    if (scenes.length) fillSelect(element("scene"), scenes, controls.scene);
    const garment = controls.kind === "garment";
    const title = garment ? "PhysAvatar garment drag-and-force demo" : "PIE-NeRF drag-and-force demo";
    element("title").textContent = title;
    document.title = title;
    element("dragged").textContent = garment ? "garment" : "body";
    element("garment-panel").hidden = !garment;
    for (const node of document.querySelectorAll(".body-only")) node.hidden = garment;
    if (garment) {
      element("frame").max = controls.frames;
      for (const [name, slider] of Object.entries(garmentSliders)) {
        const input = element(name);
        const value = controls[name];
        if (document.activeElement !== input) input.value = slider.toSlider ? slider.toSlider(value) : value;
        element(`${name}-value`).textContent = slider.text(value);
      }
      fillSelect(element("motion"), controls.motions, controls.motion);
      fillSelect(element("preset"), controls.presets.concat(controls.presets.includes(controls.preset) ? [] : [controls.preset]), controls.preset);
      fillSelect(element("render_mode"), controls.render_modes, controls.render_mode);
      element("play").classList.toggle("active", controls.playing);
      element("pause").classList.toggle("active", !controls.playing);
      return;
    }
    for (const [name, slider] of Object.entries(sliders)) {
      const input = element(name);
      const value = controls[name];
      if (document.activeElement !== input) input.value = slider.toSlider ? slider.toSlider(value) : value;
      element(`${name}-value`).textContent = slider.text(value);
    }
    fillSelect(element("model"), controls.models, controls.model);
    fillSelect(element("render_mode"), controls.render_modes, controls.render_mode);
  }
})();
