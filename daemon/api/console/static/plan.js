// The plan of a job as a top view (SVG): both AGVs' stations in step order from GET /v1/jobs/{id}/plan and
// the robots' odometry poses from GET /v1/devices. Floor frame F: x to the right, y up, mm in, m on the axes.
"use strict";

const SVG_NS = "http://www.w3.org/2000/svg";
const ROBOT_COLOUR = { measure: "#1d5fbf", tracking: "#c0211b" };
const ROBOT_NAME = { measure: "measurement AGV", tracking: "tracking AGV" };

function svgElement(tag, attrs, text) {
  const e = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, String(v));
  if (text !== undefined) e.textContent = text;
  return e;
}

function robotPoses(plan, devices) {
  // robot -> {x_mm, y_mm, heading_rad} from the chassis devices' detail, where they report one
  const poses = {};
  for (const [robot, name] of Object.entries(plan.chassis_devices)) {
    const d = devices && devices.devices.find((x) => x.name === name);
    if (d && Number.isFinite(d.detail.x_mm) && Number.isFinite(d.detail.y_mm)) {
      poses[robot] = { x_mm: d.detail.x_mm, y_mm: d.detail.y_mm, heading_rad: d.detail.heading_rad || 0 };
    }
  }
  return poses;
}

function activeStations(plan, currentStep) {
  // step index of the station each robot stands at (or moves to) at currentStep
  const active = {};
  if (currentStep == null) return active;
  for (const s of plan.stations) if (s.step <= currentStep) active[s.robot] = s.step;
  return active;
}

function drawPlan(svg, plan, currentStep, devices) {
  const poses = robotPoses(plan, devices);
  const pts = plan.stations.map((s) => [s.x_mm, s.y_mm]).concat(Object.values(poses).map((p) => [p.x_mm, p.y_mm]));
  if (!pts.length) return;
  const xs = pts.map((p) => p[0]), ys = pts.map((p) => p[1]);
  const pad = 600;  // mm around the stations
  const x0 = Math.min(...xs) - pad, x1 = Math.max(...xs) + pad, y0 = Math.min(...ys) - pad, y1 = Math.max(...ys) + pad;
  const width = x1 - x0, height = y1 - y0;
  const unit = Math.max(width, height) / 60;  // symbol size, mm
  svg.setAttribute("viewBox", `${x0} ${-y1} ${width} ${height}`);
  svg.setAttribute("preserveAspectRatio", "xMidYMid meet");
  const g = svgElement("g", { transform: "scale(1,-1)" });  // y up
  const grid = svgElement("g", { stroke: "#dde2e8", "stroke-width": unit / 10 });
  for (let x = Math.ceil(x0 / 1000) * 1000; x <= x1; x += 1000) grid.append(svgElement("line", { x1: x, y1: y0, x2: x, y2: y1 }));
  for (let y = Math.ceil(y0 / 1000) * 1000; y <= y1; y += 1000) grid.append(svgElement("line", { x1: x0, y1: y, x2: x1, y2: y }));
  g.append(grid);

  const active = activeStations(plan, currentStep);
  for (const robot of ["measure", "tracking"]) {
    const stations = plan.stations.filter((s) => s.robot === robot);
    if (stations.length > 1) {
      g.append(svgElement("polyline", { points: stations.map((s) => `${s.x_mm},${s.y_mm}`).join(" "), fill: "none",
        stroke: ROBOT_COLOUR[robot], "stroke-width": unit / 6, "stroke-dasharray": `${unit / 2} ${unit / 3}` }));
    }
    stations.forEach((s, k) => {
      const on = active[robot] === s.step, r = on ? unit * 0.9 : unit * 0.6;
      const attrs = { fill: on ? ROBOT_COLOUR[robot] : "#fff", stroke: ROBOT_COLOUR[robot], "stroke-width": unit / 5 };
      const mark = robot === "measure"
        ? svgElement("rect", { ...attrs, x: s.x_mm - r, y: s.y_mm - r, width: 2 * r, height: 2 * r })
        : svgElement("circle", { ...attrs, cx: s.x_mm, cy: s.y_mm, r });
      mark.append(svgElement("title", {}, `${ROBOT_NAME[robot]} station ${k + 1} (step ${s.step + 1}, ` +
        `${s.scan_steps.length} scans)`));
      g.append(mark);
      g.append(svgElement("text", { x: s.x_mm + r * 1.3, y: -(s.y_mm + r * 1.3), transform: "scale(1,-1)",
        "font-size": unit * 1.6, fill: ROBOT_COLOUR[robot] }, `${robot === "measure" ? "M" : "T"}${k + 1}`));
    });
  }
  const moving = new Set((devices && devices.moving) || []);
  for (const [robot, p] of Object.entries(poses)) {
    const c = Math.cos(p.heading_rad), s = Math.sin(p.heading_rad), L = unit * 2.2, W = unit * 1.2;
    const tri = [[L, 0], [-L / 2, W], [-L / 2, -W]].map(([a, b]) => `${p.x_mm + a * c - b * s},${p.y_mm + a * s + b * c}`);
    const body = svgElement("polygon", { points: tri.join(" "), fill: ROBOT_COLOUR[robot], stroke: moving.has(robot) ? "#f2b600" : "#000",
      "stroke-width": moving.has(robot) ? unit / 2 : unit / 6, "data-robot": robot });
    body.append(svgElement("title", {}, `${ROBOT_NAME[robot]} now${moving.has(robot) ? " (moving)" : ""}`));
    g.append(body);
  }
  svg.replaceChildren(g);
}
