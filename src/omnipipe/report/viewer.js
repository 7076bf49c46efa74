// omnipipe report: a dependency-free WebGL viewer for the textured pipe model.
// Data come from <script type="application/json" id="model-data">: positions (flat
// xyz, mm), uvs (flat uv), indices (flat triangles), texture (data URI), centre,
// radius, markers ([{label, position: [x, y, z] mm, href}]: the defects and the joints/laterals, drawn as
// labels that follow the model and link to their table rows). Drag to orbit, shift+drag or right-drag to pan, wheel to zoom, double
// click to reset.
(function () {
  "use strict";
  var canvas = document.getElementById("model-view");
  var status = document.getElementById("model-status");
  var dataNode = document.getElementById("model-data");
  if (!canvas || !dataNode) { return; }
  var data = JSON.parse(dataNode.textContent);
  var gl = canvas.getContext("webgl", { antialias: true, preserveDrawingBuffer: true });
  if (!gl) { status.textContent = "WebGL is not available in this browser."; return; }
  var uintIndex = gl.getExtension("OES_element_index_uint");

  var vs = [
    "attribute vec3 aPos; attribute vec2 aUv; attribute vec3 aNormal;",
    "uniform mat4 uMvp; uniform mat4 uView;",
    "varying vec2 vUv; varying float vShade;",
    "void main() {",
    "  vUv = aUv;",
    "  vec3 n = normalize((uView * vec4(aNormal, 0.0)).xyz);",
    "  vShade = 0.55 + 0.45 * abs(n.z);",
    "  gl_Position = uMvp * vec4(aPos, 1.0);",
    "}"].join("\n");
  var fs = [
    "precision mediump float;",
    "uniform sampler2D uTex; uniform float uUseTex;",
    "varying vec2 vUv; varying float vShade;",
    "void main() {",
    "  vec3 c = mix(vec3(0.75, 0.72, 0.68), texture2D(uTex, vUv).rgb, uUseTex);",
    "  gl_FragColor = vec4(c * vShade, 1.0);",
    "}"].join("\n");

  function compile(type, src) {
    var s = gl.createShader(type);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) { throw new Error(gl.getShaderInfoLog(s)); }
    return s;
  }
  var prog = gl.createProgram();
  gl.attachShader(prog, compile(gl.VERTEX_SHADER, vs));
  gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, fs));
  gl.linkProgram(prog);
  gl.useProgram(prog);

  var pos = new Float32Array(data.positions);
  var uv = new Float32Array(data.uvs);
  var idx = (uintIndex ? new Uint32Array(data.indices) : new Uint16Array(data.indices));
  // Vertex normals: area-weighted sum of face normals.
  var nrm = new Float32Array(pos.length);
  for (var f = 0; f < idx.length; f += 3) {
    var a = idx[f] * 3, b = idx[f + 1] * 3, c = idx[f + 2] * 3;
    var ux = pos[b] - pos[a], uy = pos[b + 1] - pos[a + 1], uz = pos[b + 2] - pos[a + 2];
    var vx = pos[c] - pos[a], vy = pos[c + 1] - pos[a + 1], vz = pos[c + 2] - pos[a + 2];
    var nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
    [a, b, c].forEach(function (k) { nrm[k] += nx; nrm[k + 1] += ny; nrm[k + 2] += nz; });
  }
  function buffer(arr, target) {
    var buf = gl.createBuffer();
    gl.bindBuffer(target || gl.ARRAY_BUFFER, buf);
    gl.bufferData(target || gl.ARRAY_BUFFER, arr, gl.STATIC_DRAW);
    return buf;
  }
  function attrib(name, buf, size) {
    var loc = gl.getAttribLocation(prog, name);
    gl.bindBuffer(gl.ARRAY_BUFFER, buf);
    gl.enableVertexAttribArray(loc);
    gl.vertexAttribPointer(loc, size, gl.FLOAT, false, 0, 0);
  }
  attrib("aPos", buffer(pos), 3);
  attrib("aUv", buffer(uv), 2);
  attrib("aNormal", buffer(nrm), 3);
  buffer(idx, gl.ELEMENT_ARRAY_BUFFER);

  var tex = gl.createTexture();
  var useTex = 0.0;
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, 1, 1, 0, gl.RGB, gl.UNSIGNED_BYTE, new Uint8Array([190, 180, 170]));
  if (data.texture) {
    var img = new Image();
    img.onload = function () {
      gl.bindTexture(gl.TEXTURE_2D, tex);
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, img);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
      useTex = 1.0;
      draw();
    };
    img.src = data.texture;
  }

  // Camera: orbit around the model centre.
  var state = { yaw: 0.6, pitch: 0.35, dist: 2.6 * data.radius, panX: 0, panY: 0 };
  var initial = JSON.parse(JSON.stringify(state));
  function mul(a, b) {
    var o = new Float32Array(16);
    for (var i = 0; i < 4; i++) for (var j = 0; j < 4; j++) {
      var s = 0; for (var k = 0; k < 4; k++) { s += a[k * 4 + j] * b[i * 4 + k]; } o[i * 4 + j] = s;
    }
    return o;
  }
  function perspective(fovy, aspect, near, far) {
    var f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0]);
  }
  function view() {
    var cy = Math.cos(state.yaw), sy = Math.sin(state.yaw), cp = Math.cos(state.pitch), sp = Math.sin(state.pitch);
    // Rotation: yaw about the model's y axis, then pitch about x; then translate.
    var r = new Float32Array([cy, sp * sy, -cp * sy, 0, 0, cp, sp, 0, sy, -sp * cy, cp * cy, 0, 0, 0, 0, 1]);
    var t = new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, -data.centre[0], -data.centre[1], -data.centre[2], 1]);
    var back = new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, state.panX, state.panY, -state.dist, 1]);
    return mul(back, mul(r, t));
  }
  var markers = (data.markers || []).map(function (m) {
    var a = document.createElement("a");
    a.className = "marker";
    a.textContent = m.label;
    a.href = m.href || "#";
    a.title = "go to " + m.label + " in the defect table";
    canvas.parentNode.appendChild(a);
    return { el: a, p: m.position };
  });
  function placeMarkers(mvp, w, h) {
    markers.forEach(function (m) {
      var x = m.p[0], y = m.p[1], z = m.p[2];
      var cx = mvp[0] * x + mvp[4] * y + mvp[8] * z + mvp[12];
      var cy = mvp[1] * x + mvp[5] * y + mvp[9] * z + mvp[13];
      var cw = mvp[3] * x + mvp[7] * y + mvp[11] * z + mvp[15];
      if (cw <= 0) { m.el.style.display = "none"; return; }
      m.el.style.display = "";
      m.el.style.left = ((cx / cw + 1) / 2 * w).toFixed(1) + "px";
      m.el.style.top = ((1 - cy / cw) / 2 * h).toFixed(1) + "px";
    });
  }
  function draw() {
    var w = canvas.clientWidth, h = canvas.clientHeight;
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    gl.viewport(0, 0, w, h);
    gl.clearColor(0.12, 0.13, 0.15, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    var v = view();
    var p = perspective(0.8, w / Math.max(h, 1), data.radius * 0.02, data.radius * 50);
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "uMvp"), false, mul(p, v));
    gl.uniformMatrix4fv(gl.getUniformLocation(prog, "uView"), false, v);
    gl.uniform1f(gl.getUniformLocation(prog, "uUseTex"), useTex);
    gl.drawElements(gl.TRIANGLES, idx.length, uintIndex ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT, 0);
    placeMarkers(mul(p, v), w, h);
    status.textContent = (idx.length / 3) + " triangles, " + (pos.length / 3) + " vertices" +
      (useTex ? ", textured" : "") + (markers.length ? ", " + markers.length + " marker(s)" : "") + ". Drag: orbit, shift+drag: pan, wheel: zoom, double-click: reset.";
    canvas.setAttribute("data-rendered", "1");
  }
  var drag = null;
  canvas.addEventListener("mousedown", function (e) { drag = { x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button === 2 }; });
  window.addEventListener("mouseup", function () { drag = null; });
  window.addEventListener("mousemove", function (e) {
    if (!drag) { return; }
    var dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    drag.x = e.clientX; drag.y = e.clientY;
    if (drag.pan) { state.panX += dx * state.dist / 800; state.panY -= dy * state.dist / 800; }
    else { state.yaw += dx * 0.01; state.pitch = Math.max(-1.5, Math.min(1.5, state.pitch + dy * 0.01)); }
    draw();
  });
  canvas.addEventListener("wheel", function (e) { e.preventDefault(); state.dist *= Math.exp(e.deltaY * 0.001); draw(); }, { passive: false });
  canvas.addEventListener("dblclick", function () { state = JSON.parse(JSON.stringify(initial)); draw(); });
  canvas.addEventListener("contextmenu", function (e) { e.preventDefault(); });
  window.addEventListener("resize", draw);
  draw();
})();
