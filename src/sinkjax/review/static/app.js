// The review page: frame list, viewer, label panel, time series, jobs. Talks to /api/* only;
// every number it shows about a label is computed by the server (sinkjax.geometry).
import { Viewer, Editor, drawEstimate, el } from './editor.js';

const $ = (id) => document.getElementById(id);
const S = { frames: [], recs: [], table: [], order: [], cur: 0, sort: { key: 'suspicion', dir: -1 },
  mode: 'review', jobState: null, seq: 0 };
const viewer = new Viewer($('view'));
const editor = new Editor(viewer, $('editor'), onEdit);
viewer.onZoom = () => { drawFrame(); editor.render(); };

async function api(path, body) {
  const opt = body === undefined ? {} : { method: 'POST', headers: { 'Content-Type': 'application/json' },
    body: JSON.stringify(body) };
  const r = await fetch(path, opt);
  const data = await r.json().catch(() => ({ error: r.statusText }));
  if (!r.ok) throw new Error(data.error || r.statusText);
  return data;
}
const say = (msg) => { $('status').textContent = msg || ''; };
const fmt = (v, d = 2) => (v == null ? '' : Number(v).toFixed(d));
const num = (v) => (v == null || v === '' ? null : Number(v));
const entry = (i) => S.table[i];
const res = (i) => (S.table[i] ? S.table[i].result : null);

// ------------------------------------------------------------------------- frame list
function sortValue(i, key) {
  const t = entry(i), r = t.result || {};
  if (key === 'suspicion') return t.suspicion;
  if (key === 'index') return i;
  if (key === 'name') return S.frames[i].name;
  if (key === 'status') return r.status ?? null;
  if (key === 'sigma') return r.sinkage_std_mm ?? null;
  return r[key] ?? null;
}
function sortOrder() {
  const { key, dir } = S.sort;
  S.order = S.frames.map((f) => f.index).sort((a, b) => {
    const x = sortValue(a, key), y = sortValue(b, key);
    if (x === y) return a - b;
    if (x === null) return 1;
    if (y === null) return -1;
    return (x < y ? -1 : 1) * dir;
  });
}
function renderTable() {
  const body = $('frames').tBodies[0];
  body.replaceChildren();
  for (const i of S.order) {
    const t = entry(i), r = t.result || {}, tr = body.insertRow();
    tr.dataset.index = i;
    if (i === S.cur) tr.className = 'current';
    if (r.status && r.status !== 'ok' && r.status !== 'no_contact') tr.classList.add('bad');
    const cells = [
      [t.suspicion > 0 ? (t.suspicion >= 100 ? '!!' : '!') : '', 'flag'],
      [i, 'num'], [S.frames[i].name.split('/').pop(), 'name'], [r.status || '—', 'st'],
      [fmt(r.sinkage_mm), 'num'], [fmt(r.theta1_deg, 1), 'num'], [fmt(r.theta2_deg, 1), 'num'],
      [fmt(r.sinkage_std_mm), 'num']];
    for (const [text, cls] of cells) {
      const td = tr.insertCell();
      td.textContent = text;
      td.className = cls;
    }
    tr.cells[0].title = t.reasons.join('\n');
    tr.cells[2].title = S.frames[i].name;
    if (t.label) tr.cells[2].classList.add('labelled');
    tr.onclick = () => open(i);
  }
  for (const th of $('frames').tHead.rows[0].cells) {
    th.className = th.dataset.key === S.sort.key ? (S.sort.dir > 0 ? 'sorted asc' : 'sorted') : '';
  }
}
$('frames').tHead.onclick = (e) => {
  const key = e.target.dataset.key;
  if (!key) return;
  S.sort = { key, dir: S.sort.key === key ? -S.sort.dir : (key === 'suspicion' ? -1 : 1) };
  sortOrder();
  renderTable();
};

// ------------------------------------------------------------------------- one frame
function drawFrame() {
  const f = S.frames[S.cur];
  if (!f) return;
  const rec = S.recs[f.recording];
  drawEstimate(viewer, $('estimate'), S.mode === 'review' ? res(S.cur) : null, rec.confidence_rect);
}
function renderDetails() {
  const i = S.cur, f = S.frames[i], t = entry(i), r = t.result;
  const box = $('details');
  box.replaceChildren();
  const h = document.createElement('h2');
  h.textContent = `#${i} ${f.name}`;
  box.append(h);
  const p = document.createElement('p');
  if (!r) p.textContent = 'not measured (press Measure)';
  else {
    const sd = (v, s, d) => (v == null ? '—' : `${fmt(v, d)}${s == null ? '' : ` ± ${fmt(s, d)}`}`);
    p.innerText = `${r.status}${r.message ? `: ${r.message}` : ''}\n` +
      `z0 ${sd(r.sinkage_mm, r.sinkage_std_mm, 2)} mm\nθ1 ${sd(r.theta1_deg, r.theta1_std_deg, 2)}°\n` +
      `θ2 ${sd(r.theta2_deg, r.theta2_std_deg, 2)}°\n` +
      (r.radius_px == null ? '' : `rim (${fmt(r.center_x_px, 1)}, ${fmt(r.center_y_px, 1)}) r ${fmt(r.radius_px, 1)} px`);
  }
  box.append(p);
  if (t.reasons.length) {
    const ul = document.createElement('ul');
    for (const reason of t.reasons) ul.appendChild(document.createElement('li')).textContent = reason;
    box.append(ul);
  }
  if (t.label) {
    const q = document.createElement('p');
    q.textContent = `label: z0 ${t.label.sinkage_mm} mm, θ1 ${t.label.theta1_deg}°, θ2 ${t.label.theta2_deg}°`;
    box.append(q);
  }
}
async function open(i) {
  if (i == null || !S.frames[i]) return;
  S.cur = i;
  $('framename').textContent = `#${i} ${S.frames[i].name}`;
  renderTable();
  const row = $('frames').querySelector('tr.current');
  if (row) row.scrollIntoView({ block: 'nearest' });
  renderDetails();
  renderSeries();
  editor.clear();
  try {
    await viewer.load(S.frames[i].url);
  } catch (e) { say(e.message); }
  if (S.cur !== i) return;
  drawFrame();
  if (S.mode === 'label') await startLabel();
}
function step(d) {
  const k = S.order.indexOf(S.cur);
  open(S.order[Math.min(Math.max(k + d, 0), S.order.length - 1)]);
}

// ------------------------------------------------------------------------- labelling
async function startLabel() {
  const i = S.cur;
  $('labelsource').textContent = '(loading…)';
  $('saved').textContent = '';
  try {
    const start = await api(`/api/frames/${i}/start`);
    if (S.cur !== i || S.mode !== 'label') return;
    $('labelsource').textContent = `from ${start.source}`;
    editor.set(start);
  } catch (e) { say(e.message); }
}
let pending = null;
function onEdit(now) {
  clearTimeout(pending);
  pending = setTimeout(compute, now ? 0 : 60);
}
async function compute() {
  if (!editor.g) return;
  const seq = ++S.seq;
  document.body.dataset.pending = '1';
  try {
    const v = await api('/api/geometry', { frame: S.cur, ...editor.geometry() });
    if (seq !== S.seq) return;
    $('lz0').textContent = fmt(v.sinkage_mm, 2);
    $('lt1').textContent = fmt(v.theta1_deg, 2);
    $('lt2').textContent = fmt(v.theta2_deg, 2);
    editor.line = v.line_px;
    editor.render();
    say(v.contact ? '' : 'the soil line does not reach inside the rim: no contact');
  } catch (e) { say(e.message); }
  if (seq === S.seq) delete document.body.dataset.pending;
}
async function save() {
  if (S.mode !== 'label' || !editor.g) return;
  try {
    const r = await api('/api/labels', { frame: S.cur, ...editor.geometry() });
    $('saved').textContent = `saved ${r.row.image}: z0 ${r.row.sinkage_mm} mm, θ1 ${r.row.theta1_deg}°, ` +
      `θ2 ${r.row.theta2_deg}° → ${r.labels}`;
    entry(S.cur).label = r.row;
    renderTable();
    renderDetails();
    renderSeries();
  } catch (e) { say(`not saved: ${e.message}`); }
}
function setMode(mode) {
  S.mode = mode;
  $('mode').classList.toggle('on', mode === 'label');
  $('labelpanel').hidden = mode !== 'label';
  $('view').classList.toggle('label', mode === 'label');
  editor.clear();
  drawFrame();
  if (mode === 'label') startLabel();
}

// ------------------------------------------------------------------------- time series
const SERIES = [['sinkage_mm', 'sinkage_std_mm', 'z0 (mm)'], ['theta1_deg', 'theta1_std_deg', 'θ1 (°)'],
  ['theta2_deg', 'theta2_std_deg', 'θ2 (°)']];
function renderSeries() {
  const box = $('series');
  box.replaceChildren();
  const n = S.frames.length;
  for (const [key, skey, title] of SERIES) {
    const W = Math.max(box.clientWidth / 3 - 8, 120), H = Math.max(box.clientHeight - 10, 80);
    const svg = el('svg', { class: 'plot', viewBox: `0 0 ${W} ${H}` }, box);
    const pts = [], labels = [];
    S.table.forEach((t, i) => {
      const r = t.result;
      if (r && r.status === 'ok' && r[key] != null) pts.push([i, r[key], r[skey] ?? 0]);
      if (t.label && num(t.label[key]) != null) labels.push([i, num(t.label[key])]);
    });
    const ys = pts.flatMap(([, v, s]) => [v - s, v + s]).concat(labels.map(([, v]) => v));
    let lo = Math.min(...ys), hi = Math.max(...ys);
    if (!ys.length) { lo = 0; hi = 1; }
    if (hi - lo < 1e-6) { lo -= 1; hi += 1; }
    const pad = 0.08 * (hi - lo);
    lo -= pad; hi += pad;
    const L = 38, R = 6, T = 16, B = 14;
    const X = (i) => L + (n > 1 ? (i / (n - 1)) * (W - L - R) : (W - L - R) / 2);
    const Y = (v) => T + (1 - (v - lo) / (hi - lo)) * (H - T - B);
    el('rect', { x: L, y: T, width: W - L - R, height: H - T - B, fill: '#fafbfc', stroke: '#dde' }, svg);
    el('text', { x: L, y: 11 }, svg).textContent = title;
    for (const v of [lo + pad, hi - pad]) {
      el('text', { x: L - 3, y: Y(v) + 4, 'text-anchor': 'end' }, svg).textContent = fmt(v, 1);
    }
    el('line', { x1: X(S.cur), x2: X(S.cur), y1: T, y2: H - B, stroke: '#e0a800', 'stroke-width': 2 }, svg);
    // sigma band and line, broken where frames are not measured
    const runs = [];
    for (const p of pts) {
      const last = runs.at(-1);
      if (last && p[0] === last.at(-1)[0] + 1) last.push(p); else runs.push([p]);
    }
    for (const run of runs) {
      const up = run.map(([i, v, s]) => `${X(i)},${Y(v + s)}`);
      const down = run.slice().reverse().map(([i, v, s]) => `${X(i)},${Y(v - s)}`);
      el('polygon', { points: up.concat(down).join(' '), fill: 'rgba(60,120,220,0.22)', stroke: 'none' }, svg);
      el('polyline', { points: run.map(([i, v]) => `${X(i)},${Y(v)}`).join(' '), fill: 'none',
        stroke: '#3c78dc', 'stroke-width': 1.5 }, svg);
    }
    for (const [i, v] of pts) {
      const c = el('circle', { class: 'pt', cx: X(i), cy: Y(v), r: i === S.cur ? 4.5 : 3,
        fill: entry(i).suspicion > 0 ? '#e53935' : '#3c78dc', 'data-index': i }, svg);
      c.appendChild(el('title')).textContent = `#${i} ${fmt(v)}`;
      c.onclick = () => open(i);
    }
    for (const [i, v] of labels) {
      const d = 4;
      el('path', { d: `M${X(i)},${Y(v) - d}l${d},${d}l${-d},${d}l${-d},${-d}z`, fill: '#ff8f00',
        'pointer-events': 'none' }, svg);
    }
    svg.onclick = (e) => {
      if (e.target.classList.contains('pt')) return;
      const x = (e.offsetX / svg.clientWidth) * W;
      open(Math.round(Math.min(Math.max((x - L) / (W - L - R), 0), 1) * (n - 1)));
    };
  }
}

// ------------------------------------------------------------------------- jobs
async function loadTable() {
  S.table = await api('/api/table');
  sortOrder();
  renderTable();
  renderSeries();
  renderDetails();
  drawFrame();
}
function showCalibration(job) {
  const box = $('calibration');
  box.replaceChildren();
  const r = job.result;
  if (!r) return;
  const h = document.createElement('h2');
  h.textContent = 'Calibration';
  box.append(h);
  const t = document.createElement('table');
  t.className = 'values';
  t.innerHTML = '<tr><th></th><th>before</th><th>after</th></tr>';
  for (const [k, name, d] of [['sinkage_mm', 'z0 mm', 2], ['theta1_deg', 'θ1 °', 2], ['theta2_deg', 'θ2 °', 2],
    ['n_ok', 'frames ok', 0]]) {
    const row = t.insertRow();
    row.insertCell().textContent = name;
    row.insertCell().textContent = fmt(r.before[k], d);
    row.insertCell().textContent = fmt(r.after[k], d);
  }
  box.append(t);
  const p = document.createElement('p');
  p.textContent = `median |error| on the labelled frames; loss ${fmt(r.loss_before, 3)} → ` +
    `${fmt(r.loss_after, 3)}; rig written to ${r.rig_path}; frames re-measured with it.`;
  box.append(p);
}
async function pollJob() {
  let job;
  try { job = await api('/api/job'); } catch (e) { say(e.message); return; }
  const running = job.state === 'running';
  $('jobbar').hidden = job.state === 'idle';
  $('jobbar').value = job.progress || 0;
  $('jobtext').textContent = job.kind ? `${job.kind}: ${job.state}${job.message ? ` — ${job.message}` : ''}` : '';
  document.body.dataset.job = job.state;
  $('measure').disabled = $('calibrate').disabled = running;
  if (S.jobState === 'running' && !running) {
    await loadTable();
    if (job.kind === 'calibrate' && job.state === 'done') showCalibration(job);
  }
  S.jobState = job.state;
  if (running) setTimeout(pollJob, 400);
}
async function startJob(path, body) {
  try {
    await api(path, body);
    S.jobState = 'running';
    pollJob();
  } catch (e) { say(e.message); }
}

// ------------------------------------------------------------------------- wiring
$('measure').onclick = () => startJob('/api/measure', {});
$('calibrate').onclick = () => startJob('/api/calibrate', { steps: Number($('steps').value) });
$('mode').onclick = () => setMode(S.mode === 'label' ? 'review' : 'label');
$('save').onclick = save;
$('reset').onclick = () => S.mode === 'label' && startLabel();
$('clearpts').onclick = () => { if (editor.g) { editor.g.points = []; editor.render(); onEdit(true); } };
$('prev').onclick = () => step(-1);
$('next').onclick = () => step(1);
$('zoomin').onclick = () => viewer.zoomBy(1 / 1.5);
$('zoomout').onclick = () => viewer.zoomBy(1.5);
$('zoomfit').onclick = () => viewer.fit();
document.addEventListener('keydown', (e) => {
  if (e.target.closest('input, textarea') || e.ctrlKey || e.metaKey || e.altKey) return;
  const keys = { ArrowRight: () => step(1), ArrowDown: () => step(1), j: () => step(1),
    ArrowLeft: () => step(-1), ArrowUp: () => step(-1), k: () => step(-1),
    l: () => setMode(S.mode === 'label' ? 'review' : 'label'), s: save, r: () => S.mode === 'label' && startLabel(),
    0: () => viewer.fit(), '+': () => viewer.zoomBy(1 / 1.5), '=': () => viewer.zoomBy(1 / 1.5),
    '-': () => viewer.zoomBy(1.5) };
  if (keys[e.key]) { e.preventDefault(); keys[e.key](); }
});
window.addEventListener('resize', renderSeries);

(async () => {
  try {
    const info = await api('/api/session');
    S.frames = info.frames;
    S.recs = info.recordings;
    document.title = `sinkjax review — ${S.frames.length} frames`;
    await loadTable();
    await open(S.order[0]);
    document.body.dataset.ready = '1';
    pollJob();
  } catch (e) { say(e.message); }
})();
