// The 3D view of a finished job's cloud (WebGL 1, written here): points coloured by their deviation from CAD
// with the report's colour map and scale, turned by dragging, zoomed by wheel, pinch or buttons.
// Input: the binary of GET /v1/jobs/{id}/view (docs/console.md): magic "TSV1", uint32 header length, JSON
// header, float32 x y z (mm, relative to origin_mm), float32 deviation (mm) when the header says so.
"use strict";

const cloudView = (() => {
  const VERTEX = `
    attribute vec3 position;
    attribute float deviation;
    uniform mat4 mvp;
    uniform float pointSize;
    uniform vec2 scale;          // colour scale, mm (low, high)
    uniform vec3 stops[5];       // the report's colour map, evenly spaced from low to high
    uniform bool hasDeviation;
    uniform float zRange;        // without deviations: shade by height, mm
    varying vec3 colour;
    void main() {
      gl_Position = mvp * vec4(position, 1.0);
      gl_PointSize = pointSize;
      if (hasDeviation) {
        float t = clamp((deviation - scale.x) / (scale.y - scale.x), 0.0, 1.0) * 4.0;
        colour = t < 1.0 ? mix(stops[0], stops[1], t) : t < 2.0 ? mix(stops[1], stops[2], t - 1.0)
               : t < 3.0 ? mix(stops[2], stops[3], t - 2.0) : mix(stops[3], stops[4], t - 3.0);
      } else {
        colour = vec3(0.55 + 0.4 * clamp(position.z / zRange, -0.5, 0.5));
      }
    }`;
  const FRAGMENT = `
    precision mediump float;
    varying vec3 colour;
    void main() { gl_FragColor = vec4(colour, 1.0); }`;

  let gl = null, canvas = null, program = null, count = 0, radius = 1;
  const camera = { yaw: -2.3, pitch: 0.45, distance: 3, pointSize: 2 };
  const pointers = new Map();

  // ---------------------------------------------------------------- matrices (column-major, as WebGL reads)
  function perspective(fovy, aspect, near, far) {
    const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0];
  }
  function lookAt(eye, up) {  // looking at the origin
    const norm = (v) => { const l = Math.hypot(...v); return v.map((x) => x / l); };
    const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    const z = norm(eye), x = norm(cross(up, z)), y = cross(z, x);
    return [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
  }
  function multiply(a, b) {
    const out = new Array(16).fill(0);
    for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) for (let k = 0; k < 4; k++) out[c * 4 + r] += a[k * 4 + r] * b[c * 4 + k];
    return out;
  }

  // ---------------------------------------------------------------- GL set-up
  function compile(type, source) {
    const s = gl.createShader(type);
    gl.shaderSource(s, source);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  }

  function init() {
    gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, antialias: false });
    if (!gl) throw new Error("this browser has no WebGL: the 3D view cannot be drawn");
    program = gl.createProgram();
    gl.attachShader(program, compile(gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(program, compile(gl.FRAGMENT_SHADER, FRAGMENT));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
    gl.useProgram(program);
    gl.enable(gl.DEPTH_TEST);
  }

  function hexRgb(hex) {
    const v = parseInt(hex.slice(1), 16);
    return [(v >> 16) / 255, ((v >> 8) & 255) / 255, (v & 255) / 255];
  }

  function buffer(name, data, size) {
    const b = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, b);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    const loc = gl.getAttribLocation(program, name);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
  }

  function parse(arrayBuffer) {
    const bytes = new Uint8Array(arrayBuffer);
    if (String.fromCharCode(...bytes.subarray(0, 4)) !== "TSV1") throw new Error("not a tandemscan cloud view");
    const length = new DataView(arrayBuffer).getUint32(4, true);
    const header = JSON.parse(new TextDecoder().decode(bytes.subarray(8, 8 + length)));
    const n = header.points, start = 8 + length;
    const xyz = new Float32Array(arrayBuffer, start, n * 3);
    const deviation = header.deviation ? new Float32Array(arrayBuffer, start + 12 * n, n) : new Float32Array(n);
    return { header, xyz, deviation };
  }

  // ---------------------------------------------------------------- drawing
  function draw() {
    if (!gl || !count) return;
    const w = canvas.clientWidth * devicePixelRatio, h = canvas.clientHeight * devicePixelRatio;
    if (w && h && (canvas.width !== Math.round(w) || canvas.height !== Math.round(h))) {
      canvas.width = Math.round(w);
      canvas.height = Math.round(h);
    }
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.clearColor(0.063, 0.082, 0.11, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    const d = camera.distance * radius, cp = Math.cos(camera.pitch);
    const eye = [d * cp * Math.cos(camera.yaw), d * cp * Math.sin(camera.yaw), d * Math.sin(camera.pitch)];
    const mvp = multiply(perspective(0.8, canvas.width / canvas.height, d / 50, d + 4 * radius), lookAt(eye, [0, 0, 1]));
    gl.uniformMatrix4fv(gl.getUniformLocation(program, "mvp"), false, new Float32Array(mvp));
    gl.uniform1f(gl.getUniformLocation(program, "pointSize"), camera.pointSize * devicePixelRatio);
    gl.drawArrays(gl.POINTS, 0, count);
  }

  function show(arrayBuffer) {
    if (!gl) init();
    const { header, xyz, deviation } = parse(arrayBuffer);
    count = header.points;
    radius = 1;
    for (let i = 0; i < xyz.length; i += 3) radius = Math.max(radius, Math.hypot(xyz[i], xyz[i + 1], xyz[i + 2]));
    buffer("position", xyz, 3);
    buffer("deviation", deviation, 1);
    const scale = header.colour_scale_mm || [-1, 1];
    gl.uniform2f(gl.getUniformLocation(program, "scale"), scale[0], scale[1]);
    gl.uniform3fv(gl.getUniformLocation(program, "stops"), new Float32Array(header.colours.flatMap(hexRgb)));
    gl.uniform1i(gl.getUniformLocation(program, "hasDeviation"), header.deviation ? 1 : 0);
    gl.uniform1f(gl.getUniformLocation(program, "zRange"), radius);
    resetView();
    return header;
  }

  function resetView() {
    Object.assign(camera, { yaw: -2.3, pitch: 0.45, distance: 2.0 });
    draw();
  }

  function zoom(factor) {
    camera.distance = Math.min(20, Math.max(0.15, camera.distance * factor));
    draw();
  }

  // ---------------------------------------------------------------- input: mouse, touch, pen
  function attach(target, controls) {
    canvas = target;
    canvas.addEventListener("pointerdown", (e) => { canvas.setPointerCapture(e.pointerId); pointers.set(e.pointerId, e); });
    const release = (e) => pointers.delete(e.pointerId);
    canvas.addEventListener("pointerup", release);
    canvas.addEventListener("pointercancel", release);
    canvas.addEventListener("pointermove", (e) => {
      const last = pointers.get(e.pointerId);
      if (!last) return;
      if (pointers.size === 1) {
        camera.yaw -= (e.clientX - last.clientX) * 0.008;
        camera.pitch = Math.min(1.55, Math.max(-1.55, camera.pitch + (e.clientY - last.clientY) * 0.008));
      } else if (pointers.size === 2) {  // pinch: the change of the two fingers' distance
        const other = [...pointers.values()].find((p) => p.pointerId !== e.pointerId);
        const before = Math.hypot(last.clientX - other.clientX, last.clientY - other.clientY);
        const after = Math.hypot(e.clientX - other.clientX, e.clientY - other.clientY);
        if (before > 0 && after > 0) camera.distance = Math.min(20, Math.max(0.15, camera.distance * before / after));
      }
      pointers.set(e.pointerId, e);
      draw();
    });
    canvas.addEventListener("wheel", (e) => { e.preventDefault(); zoom(Math.exp(e.deltaY * 0.001)); }, { passive: false });
    controls.reset.addEventListener("click", resetView);
    controls.zoomIn.addEventListener("click", () => zoom(1 / 1.25));
    controls.zoomOut.addEventListener("click", () => zoom(1.25));
    controls.pointSize.addEventListener("input", () => { camera.pointSize = Number(controls.pointSize.value); draw(); });
    window.addEventListener("resize", draw);
  }

  return { attach, show };
})();
