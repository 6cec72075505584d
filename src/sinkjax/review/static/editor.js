// The frame viewer (SVG over the image, zoom and pan), the estimate's overlay, and the label
// editor (rim, A, B, soil line or soil points as draggable handles). Coordinates are image
// pixels: the SVG's user space is the image, pixel (row i, column j) centred at (x=j, y=i).
const NS = 'http://www.w3.org/2000/svg';

export function el(tag, attrs = {}, parent = null) {
  const e = document.createElementNS(NS, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}

const THIN = { 'vector-effect': 'non-scaling-stroke', fill: 'none' };

export class Viewer {
  constructor(svg) {
    this.svg = svg;
    this.img = svg.querySelector('#frameimg');
    this.size = [0, 0];
    this.view = null;
    this.onZoom = () => {};
    this.panning = null;
    svg.addEventListener('wheel', (e) => {
      e.preventDefault();
      this.zoomAt(this.toImage(e), Math.pow(1.2, e.deltaY / 100));
    }, { passive: false });
    svg.addEventListener('pointerdown', (e) => {
      if (e.button !== 0 || e.shiftKey || e.target.closest('.handle')) return;
      this.panning = { start: [e.clientX, e.clientY], view: { ...this.view }, k: this.scale() };
      svg.setPointerCapture(e.pointerId);
    });
    svg.addEventListener('pointermove', (e) => {
      if (!this.panning) return;
      const p = this.panning;
      this.setView(p.view.x - (e.clientX - p.start[0]) / p.k, p.view.y - (e.clientY - p.start[1]) / p.k,
        p.view.w, p.view.h);
    });
    svg.addEventListener('pointerup', () => { this.panning = null; });
  }

  load(url) {
    return new Promise((resolve, reject) => {
      const im = new Image();
      im.onload = () => {
        const changed = im.naturalWidth !== this.size[0] || im.naturalHeight !== this.size[1];
        this.size = [im.naturalWidth, im.naturalHeight];
        this.img.setAttribute('href', url);
        this.img.setAttribute('width', this.size[0]);
        this.img.setAttribute('height', this.size[1]);
        if (changed || !this.view) this.fit();
        resolve();
      };
      im.onerror = () => reject(new Error(`cannot load ${url}`));
      im.src = url;
    });
  }

  fit() { this.setView(-0.5, -0.5, this.size[0], this.size[1]); }
  setView(x, y, w, h) {
    this.view = { x, y, w, h };
    this.svg.setAttribute('viewBox', `${x} ${y} ${w} ${h}`);
    this.onZoom();
  }
  zoomAt(p, f) {
    const v = this.view;
    this.setView(p[0] - (p[0] - v.x) * f, p[1] - (p[1] - v.y) * f, v.w * f, v.h * f);
  }
  zoomBy(f) { const v = this.view; this.zoomAt([v.x + v.w / 2, v.y + v.h / 2], f); }
  toImage(e) {
    const pt = this.svg.createSVGPoint();
    pt.x = e.clientX; pt.y = e.clientY;
    const q = pt.matrixTransform(this.svg.getScreenCTM().inverse());
    return [q.x, q.y];
  }
  scale() { return this.svg.getScreenCTM().a || 1; } // screen px per image px
  px(n) { return n / this.scale(); }
}

export function drawEstimate(viewer, group, result, rect) {
  group.replaceChildren();
  if (rect) {
    el('rect', { ...THIN, x: rect[0] - 0.5, y: rect[1] - 0.5, width: rect[2], height: rect[3],
      stroke: '#c8c8c8', 'stroke-dasharray': '4 3' }, group);
  }
  if (!result || result.radius_px == null) return;
  const [cx, cy, r] = [result.center_x_px, result.center_y_px, result.radius_px];
  el('circle', { ...THIN, cx, cy, r, stroke: '#ffd700', 'stroke-width': 1.5 }, group);
  const s = viewer.px(6);
  el('path', { ...THIN, d: `M${cx - s},${cy}H${cx + s}M${cx},${cy - s}V${cy + s}`, stroke: '#ffd700' }, group);
  const ov = result.overlay;
  if (!ov) return;
  for (const [x, y] of ov.boundary_px || []) {
    el('circle', { cx: x, cy: y, r: viewer.px(1.6), fill: '#00e5ff' }, group);
  }
  if (ov.line_px) {
    const [[x1, y1], [x2, y2]] = ov.line_px;
    el('line', { ...THIN, x1, y1, x2, y2, stroke: '#ff40ff', 'stroke-width': 1.5 }, group);
  }
  for (const [p, name, colour] of [[ov.a_px, 'A', '#ff4040'], [ov.b_px, 'B', '#40a0ff']]) {
    if (!p) continue;
    el('circle', { cx: p[0], cy: p[1], r: viewer.px(4), fill: colour, stroke: '#000',
      'vector-effect': 'non-scaling-stroke' }, group);
    el('text', { x: p[0] + viewer.px(6), y: p[1] - viewer.px(6), fill: colour,
      'font-size': viewer.px(14), 'font-weight': 700 }, group).textContent = name;
  }
  el('text', { x: cx + viewer.px(6), y: cy - viewer.px(6), fill: '#ffd700', 'font-size': viewer.px(14),
    'font-weight': 700 }, group).textContent = 'O';
}

const sub = (p, q) => [p[0] - q[0], p[1] - q[1]];
const add = (p, q) => [p[0] + q[0], p[1] + q[1]];
const onCircle = (c, r, phi) => [c[0] + r * Math.cos(phi), c[1] + r * Math.sin(phi)];
const angleOf = (p, c) => Math.atan2(p[1] - c[1], p[0] - c[0]);

// Label geometry: rim (centre, radius), A and B on the rim (kept as angles so that they stay on
// it when the rim moves), the soil as a line through two handles or as clicked points.
export class Editor {
  constructor(viewer, group, onChange) {
    this.v = viewer;
    this.group = group;
    this.onChange = onChange;
    this.g = null;
    this.line = null; // the equivalent line's chord from the server, for drawing
    this.drag = null;
    const svg = viewer.svg;
    svg.addEventListener('pointerdown', (e) => this.down(e));
    svg.addEventListener('pointermove', (e) => this.move(e));
    svg.addEventListener('pointerup', (e) => this.up(e));
  }

  set(start) {
    const c = start.centre_px, [p, q] = start.soil_px;
    this.g = {
      centre: [...c], radius: start.radius_px,
      phiA: angleOf(start.a_px, c), phiB: angleOf(start.b_px, c), phiR: -0.75 * Math.PI,
      // The line's handles sit inside the chord, clear of A and B at its ends.
      line: [0.2, 0.8].map((t) => [0, 1].map((j) => p[j] + t * (q[j] - p[j]))), points: [],
    };
    this.line = null;
    this.render();
    this.onChange(true);
  }
  clear() { this.g = null; this.group.replaceChildren(); }
  a() { return onCircle(this.g.centre, this.g.radius, this.g.phiA); }
  b() { return onCircle(this.g.centre, this.g.radius, this.g.phiB); }

  geometry() {
    const g = this.g;
    return { centre_px: g.centre, radius_px: g.radius, a_px: this.a(), b_px: this.b(),
      soil_px: g.points.length >= 2 ? g.points : g.line };
  }

  handleAt(role) {
    const g = this.g;
    if (role === 'O') return g.centre;
    if (role === 'R') return onCircle(g.centre, g.radius, g.phiR);
    if (role === 'A') return this.a();
    if (role === 'B') return this.b();
    if (role === 'L1' || role === 'L2') return g.line[role === 'L1' ? 0 : 1];
    return g.points[Number(role.slice(1))];
  }

  down(e) {
    if (!this.g || e.button !== 0) return;
    const h = e.target.closest('.handle');
    if (h) {
      e.stopPropagation();
      this.drag = { role: h.dataset.role, start: this.v.toImage(e), g: structuredClone(this.g) };
      this.v.svg.setPointerCapture(e.pointerId);
      this.v.panning = null;
    } else if (e.shiftKey) {
      this.g.points.push(this.v.toImage(e));
      this.render();
      this.onChange(true);
    }
  }

  move(e) {
    if (!this.drag) return;
    const { role, start, g: o } = this.drag;
    const d = sub(this.v.toImage(e), start);
    const g = this.g;
    if (role === 'O') g.centre = add(o.centre, d);
    else if (role === 'R') {
      const p = add(onCircle(o.centre, o.radius, o.phiR), d);
      g.radius = Math.max(1, Math.hypot(...sub(p, o.centre)));
      g.phiR = angleOf(p, o.centre);
    } else if (role === 'A') g.phiA = angleOf(add(onCircle(o.centre, o.radius, o.phiA), d), o.centre);
    else if (role === 'B') g.phiB = angleOf(add(onCircle(o.centre, o.radius, o.phiB), d), o.centre);
    else if (role === 'L1') g.line[0] = add(o.line[0], d);
    else if (role === 'L2') g.line[1] = add(o.line[1], d);
    else if (role === 'LINE') g.line = o.line.map((p) => add(p, d));
    else g.points[Number(role.slice(1))] = add(o.points[Number(role.slice(1))], d);
    this.render();
    this.onChange(false);
  }

  up() {
    if (!this.drag) return;
    this.drag = null;
    this.onChange(true);
  }

  render() {
    const G = this.group, g = this.g, v = this.v;
    G.replaceChildren();
    if (!g) return;
    const hr = v.px(7);
    el('circle', { ...THIN, cx: g.centre[0], cy: g.centre[1], r: g.radius, stroke: '#ffe066',
      'stroke-width': 1.5, 'stroke-dasharray': '6 4' }, G);
    if (this.line) {
      const [[x1, y1], [x2, y2]] = this.line;
      el('line', { ...THIN, x1, y1, x2, y2, stroke: '#ff40ff', 'stroke-width': 2, 'stroke-dasharray': '8 4' }, G);
    }
    if (g.points.length < 2) {
      const [[x1, y1], [x2, y2]] = g.line;
      el('line', { ...THIN, x1, y1, x2, y2, stroke: '#ff40ff', 'stroke-width': 1 }, G);
      el('line', { x1, y1, x2, y2, stroke: 'transparent', 'stroke-width': v.px(10), class: 'handle',
        'data-role': 'LINE' }, G);
    }
    const handle = (role, p, fill, shape = 'circle') => {
      const attrs = { class: 'handle', 'data-role': role, fill, stroke: '#000', 'stroke-width': 1,
        'vector-effect': 'non-scaling-stroke' };
      if (shape === 'square') {
        el('rect', { ...attrs, x: p[0] - hr * 0.8, y: p[1] - hr * 0.8, width: hr * 1.6, height: hr * 1.6,
          'data-x': p[0], 'data-y': p[1] }, G);
      } else {
        el('circle', { ...attrs, cx: p[0], cy: p[1], r: shape === 'small' ? hr * 0.6 : hr,
          'data-x': p[0], 'data-y': p[1] }, G);
      }
    };
    g.points.forEach((p, i) => handle(`P${i}`, p, '#00e5ff', 'small'));
    if (g.points.length < 2) {
      handle('L1', g.line[0], '#ff40ff', 'square');
      handle('L2', g.line[1], '#ff40ff', 'square');
    }
    handle('O', g.centre, '#ffe066');
    handle('R', this.handleAt('R'), 'rgba(255,224,102,0.35)');
    handle('A', this.a(), '#ff4040');
    handle('B', this.b(), '#40a0ff');
    for (const [name, p, colour] of [['A', this.a(), '#ff4040'], ['B', this.b(), '#40a0ff'], ['O', g.centre, '#ffe066']]) {
      el('text', { x: p[0] + hr * 1.2, y: p[1] - hr * 1.2, fill: colour, 'font-size': v.px(14),
        'font-weight': 700, 'pointer-events': 'none' }, G).textContent = name;
    }
  }
}
