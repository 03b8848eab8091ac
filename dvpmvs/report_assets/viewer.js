// dvpmvs's report pages: the 3D view of a run's cloud (three.js and its OrbitControls, from
// three.bundle.js), enlargeable thumbnails, and a sweep's sortable table with its jobs' clouds side
// by side. The data comes from report_files/cloud.js (window.dvpmvsClouds), a script rather than a
// fetched file because browsers refuse fetch() from file:// pages.
(function () {
  "use strict";

  function decode(b64, Type) {
    const text = atob(b64);
    const bytes = new Uint8Array(text.length);
    for (let i = 0; i < text.length; i++) bytes[i] = text.charCodeAt(i);
    return new Type(bytes.buffer);
  }

  function option(select, value, label) {
    const o = document.createElement("option");
    o.value = value;
    o.textContent = label;
    select.appendChild(o);
    return o;
  }

  const COLOUR_NAMES = { rgb: "RGB", views: "views per point", error: "error (evaluation)" };

  // The starting view: the first camera, looking where it looked (frusta: centre, corner, ...).
  function firstCameraPose(frusta, extent) {
    if (frusta.length < 3 * 16) return null;
    const at = (i) => new THREE.Vector3(frusta[3 * i], frusta[3 * i + 1], frusta[3 * i + 2]);
    const centre = at(0);
    const corners = [at(1), at(5), at(9), at(13)];
    const middle = corners.reduce((a, c) => a.add(c), new THREE.Vector3()).multiplyScalar(0.25);
    const look = middle.clone().sub(centre).normalize();
    const up = corners[0].clone().add(corners[1]).sub(corners[2]).sub(corners[3]).normalize();
    // a step behind the camera, so that its own frustum is in the picture
    const position = centre.clone().sub(look.clone().multiplyScalar(0.15 * extent));
    return { position: position, target: centre.clone().add(look.multiplyScalar(0.5 * extent)), up: up };
  }

  function makeViewer(container, data, label) {
    const width = container.clientWidth || 640;
    const height = Math.max(320, Math.min(620, Math.round(width * 0.62)));
    const renderer = new THREE.WebGLRenderer({ antialias: false, preserveDrawingBuffer: true });
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    renderer.setSize(width, height);
    const scene = new THREE.Scene();
    scene.background = new THREE.Color(0x15181d);
    const extent = data.extent || 1;
    const camera = new THREE.PerspectiveCamera(50, width / height, extent / 2000, extent * 50);

    const sets = data.sets.map(function (set) {
      const geometry = new THREE.BufferGeometry();
      geometry.setAttribute("position", new THREE.BufferAttribute(decode(set.positions, Float32Array), 3));
      const colours = {};
      for (const mode in set.colours) {
        colours[mode] = new THREE.BufferAttribute(decode(set.colours[mode], Uint8Array), 3, true);
      }
      const first = Object.keys(colours)[0];
      geometry.setAttribute("color", colours[first]);
      const points = new THREE.Points(geometry, new THREE.PointsMaterial({ size: 2, sizeAttenuation: false,
                                                                           vertexColors: true }));
      return { set: set, geometry: geometry, colours: colours, points: points };
    });
    const frusta = decode(data.frusta, Float32Array);
    const cameraLines = new THREE.LineSegments(
      (function () {
        const g = new THREE.BufferGeometry();
        g.setAttribute("position", new THREE.BufferAttribute(frusta, 3));
        return g;
      })(),
      new THREE.LineBasicMaterial({ color: 0xff7043 }));
    scene.add(cameraLines);

    // The run's mesh (reconstruct's), lit by a light at the camera so that its shape shows.
    let mesh = null;
    if (data.mesh) {
      const g = new THREE.BufferGeometry();
      g.setAttribute("position", new THREE.BufferAttribute(decode(data.mesh.positions, Float32Array), 3));
      g.setAttribute("color", new THREE.BufferAttribute(decode(data.mesh.colours, Uint8Array), 3, true));
      g.setIndex(new THREE.BufferAttribute(decode(data.mesh.indices, Uint32Array), 1));
      g.computeVertexNormals();
      mesh = new THREE.Mesh(g, new THREE.MeshLambertMaterial({ vertexColors: true, side: THREE.DoubleSide }));
      scene.add(new THREE.AmbientLight(0xffffff, 0.45));
      const light = new THREE.DirectionalLight(0xffffff, 0.9);
      camera.add(light);
      scene.add(camera);
    }

    const controls = new THREE.OrbitControls(camera, renderer.domElement);
    const home = firstCameraPose(frusta, extent) ||
      { position: new THREE.Vector3(0, 0, -1.5 * extent), target: new THREE.Vector3(0, 0, 0), up: new THREE.Vector3(0, -1, 0) };
    function reset() {
      camera.position.copy(home.position);
      camera.up.copy(home.up);
      controls.target.copy(home.target);
      controls.update();
      render();
    }

    let current = null;
    const toolbar = document.createElement("div");
    toolbar.className = "toolbar";
    const setSelect = document.createElement("select");
    sets.forEach(function (s, i) { option(setSelect, String(i), s.set.label); });
    const colourSelect = document.createElement("select");
    const size = document.createElement("input");
    size.type = "range"; size.min = "1"; size.max = "8"; size.step = "0.5"; size.value = "2";
    const showCameras = document.createElement("input");
    showCameras.type = "checkbox"; showCameras.checked = true;
    const resetButton = document.createElement("button");
    resetButton.type = "button"; resetButton.textContent = "reset view";
    const count = document.createElement("span");
    count.className = "count";
    const showSelect = document.createElement("select");
    if (mesh) {
      option(showSelect, "points", "points");
      option(showSelect, "mesh", "mesh");
      option(showSelect, "both", "both");
    }
    function applyShow() {
      if (!mesh) return;
      const what = showSelect.value;
      mesh.visible = what !== "points";
      if (current) current.points.visible = what !== "mesh";
      render();
    }

    function choose(index) {
      if (current) scene.remove(current.points);
      current = sets[index];
      scene.add(current.points);
      colourSelect.innerHTML = "";
      Object.keys(current.colours).forEach(function (m) { option(colourSelect, m, COLOUR_NAMES[m] || m); });
      current.geometry.setAttribute("color", current.colours[colourSelect.value]);
      current.points.material.size = Number(size.value);
      if (mesh) current.points.visible = showSelect.value !== "mesh";
      const shown = current.set.count, total = current.set.total;
      count.textContent = shown < total ? shown.toLocaleString() + " of " + total.toLocaleString() + " points"
                                        : total.toLocaleString() + " points";
      render();
    }
    function render() { renderer.render(scene, camera); }

    setSelect.addEventListener("change", function () { choose(Number(setSelect.value)); });
    colourSelect.addEventListener("change", function () {
      current.geometry.setAttribute("color", current.colours[colourSelect.value]);
      render();
    });
    size.addEventListener("input", function () { current.points.material.size = Number(size.value); render(); });
    showCameras.addEventListener("change", function () { cameraLines.visible = showCameras.checked; render(); });
    resetButton.addEventListener("click", reset);
    showSelect.addEventListener("change", applyShow);
    controls.addEventListener("change", render);

    function labelled(text, element) {
      const l = document.createElement("label");
      l.textContent = text + " ";
      l.appendChild(element);
      return l;
    }
    if (label) {
      const title = document.createElement("strong");
      title.textContent = label;
      toolbar.appendChild(title);
    }
    if (mesh) toolbar.appendChild(labelled("show", showSelect));
    toolbar.appendChild(labelled("points", setSelect));
    toolbar.appendChild(labelled("colour", colourSelect));
    toolbar.appendChild(labelled("size", size));
    toolbar.appendChild(labelled("cameras", showCameras));
    toolbar.appendChild(resetButton);
    toolbar.appendChild(count);
    container.appendChild(toolbar);
    container.appendChild(renderer.domElement);

    if (mesh) {
      scene.add(mesh);
      showSelect.value = "both";
    }
    choose(0);
    applyShow();
    reset();
    // Each cloud is drawn centred on its median point (float32 precision); ``centre`` is where
    // that lies in the scene's frame, which the side-by-side views share.
    const centre = new THREE.Vector3().fromArray(data.centre || [0, 0, 0]);
    return { camera: camera, controls: controls, render: render, sets: sets, canvas: renderer.domElement,
             centre: centre, mesh: mesh, show: function (what) { showSelect.value = what; applyShow(); } };
  }

  function setupLightbox() {
    const box = document.getElementById("lightbox");
    if (!box) return;
    const image = box.querySelector("img");
    document.querySelectorAll("a.thumb").forEach(function (a) {
      a.addEventListener("click", function (event) {
        event.preventDefault();
        image.src = a.getAttribute("href");
        image.alt = a.querySelector("img").alt;
        box.hidden = false;
      });
    });
    box.addEventListener("click", function () { box.hidden = true; });
  }

  function setupSortable() {
    document.querySelectorAll("table.sortable").forEach(function (table) {
      table.querySelectorAll("th").forEach(function (th, column) {
        th.addEventListener("click", function () {
          const ascending = th.dataset.order !== "ascending";
          table.querySelectorAll("th").forEach(function (h) { delete h.dataset.order; });
          th.dataset.order = ascending ? "ascending" : "descending";
          const body = table.tBodies[0];
          const key = function (row) {
            const text = row.cells[column].textContent.trim();
            const number = parseFloat(text.replace(/,/g, ""));
            return isNaN(number) ? text : number;
          };
          Array.from(body.rows).sort(function (a, b) {
            const x = key(a), y = key(b);
            const order = (typeof x === "number" && typeof y === "number") ? x - y : String(x).localeCompare(String(y));
            return ascending ? order : -order;
          }).forEach(function (row) { body.appendChild(row); });
        });
      });
    });
  }

  const viewers = [];

  function setup() {
    setupLightbox();
    const clouds = window.dvpmvsClouds || {};
    document.querySelectorAll(".viewer").forEach(function (element) {
      const data = clouds[element.dataset.key];
      if (data) viewers.push(makeViewer(element, data, null));
    });
    document.body.dataset.ready = "yes";
  }

  // The sweep's clouds: each chosen job's cloud.js is loaded by a script element (allowed from
  // file://), then shown in its own view; moving one view moves the others.
  function setupSweep() {
    setupSortable();
    const compare = document.getElementById("compare");
    const boxes = Array.from(document.querySelectorAll(".choices input[type=checkbox]"));
    const shown = {};
    let syncing = false;
    function sync(source) {
      if (syncing) return;
      syncing = true;
      Object.values(shown).forEach(function (v) {
        if (v.viewer === source) return;
        const offset = source.centre.clone().sub(v.viewer.centre);
        v.viewer.camera.position.copy(source.camera.position).add(offset);
        v.viewer.camera.up.copy(source.camera.up);
        v.viewer.controls.target.copy(source.controls.target).add(offset);
        v.viewer.controls.update();
        v.viewer.render();
      });
      syncing = false;
    }
    function show(box) {
      const key = box.dataset.key;
      const place = document.createElement("div");
      place.className = "viewer";
      compare.appendChild(place);
      const create = function () {
        const data = (window.dvpmvsClouds || {})[key];
        if (!data) { place.textContent = "could not read " + box.dataset.src; return; }
        const viewer = makeViewer(place, data, box.dataset.label);
        viewer.controls.addEventListener("change", function () { sync(viewer); });
        shown[key] = { place: place, viewer: viewer };
        viewers.push(viewer);
        const first = Object.values(shown)[0];
        if (first && first.viewer !== viewer) sync(first.viewer);
        pending -= 1;
        if (pending === 0) document.body.dataset.ready = "yes";
      };
      if (window.dvpmvsClouds && window.dvpmvsClouds[key]) { create(); return; }
      const script = document.createElement("script");
      script.src = box.dataset.src;
      script.dataset.key = key;
      script.onload = create;
      script.onerror = function () { place.textContent = "could not load " + box.dataset.src; pending -= 1; };
      document.body.appendChild(script);
    }
    let pending = boxes.filter(function (b) { return b.checked; }).length;
    boxes.forEach(function (box) {
      if (box.checked) show(box);
      box.addEventListener("change", function () {
        if (box.checked) { pending += 1; show(box); return; }
        const entry = shown[box.dataset.key];
        if (entry) { compare.removeChild(entry.place); delete shown[box.dataset.key]; }
      });
    });
    if (pending === 0) document.body.dataset.ready = "yes";
  }

  window.dvpmvsReport = { setup: setup, setupSweep: setupSweep, viewers: viewers };
})();
