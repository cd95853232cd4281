// Live training charts (uPlot): the synchronisation figure, error against wall time, losses.
// Records are metrics.jsonl lines; any missing key is simply not plotted.
import uPlot from 'uplot';
import { h, clear } from './util.js';

const PALETTE = ['#4e9af1', '#f29e4c', '#5cc98a', '#e5607a', '#b48cf2', '#e8d25c', '#4fd1d9', '#c7a27c', '#9aa5b1', '#f27fd0'];

const SYNC_KEYS = [
  { key: 'psnr_r', label: 'L_r (rendering)' },
  { key: 'psnr_surf', label: 'L_surf (surface, over the background)' },
  { key: 'psnr_vol', label: 'L_vol (volume)' },
];
const ERR_KEYS = [
  { key: 'test_psnr', label: 'test PBR PSNR (dB)', scale: 'db' },
  { key: 'test_psnr_radiance', label: 'test radiance PSNR (dB)', scale: 'db' },
  { key: 'albedo_psnr', label: 'albedo PSNR (dB)', scale: 'db' },
  { key: 'chamfer', label: 'Chamfer', scale: 'dist' },
];

function num(v) {
  return typeof v === 'number' && Number.isFinite(v) ? v : null;
}

/**
 * One chart: a named set of series over an x key, fed by `rows` [{x, values:{key:v}}].
 * Its <figure id="chart-ID"> describes what is drawn: `data-points` (x values), `data-series`
 * (series keys, comma-separated), `data-series-points` (non-empty values of each series, same
 * order) and `data-rendered` ("true" once uPlot has drawn).
 */
class Chart {
  constructor(container, { id, title, xLabel, yLabel, log = false, y2Label = null, emptyText }) {
    this.id = id;
    this.title = title;
    this.xLabel = xLabel;
    this.yLabel = yLabel;
    this.y2Label = y2Label;
    this.log = log;
    this.rows = new Map(); // x -> {key: value}
    this.series = []; // [{key, label, scale}]
    this.plot = null;
    this.dirty = false;
    this.body = h('div', { class: 'chart-body' });
    this.empty = h('p', { class: 'muted small chart-empty' }, emptyText);
    this.el = h('figure', {
      class: 'chart', id: `chart-${id}`, dataset: { chart: id, points: '0', series: '', seriesPoints: '', rendered: 'false' },
      'aria-label': title,
    }, h('figcaption', {}, title), this.empty, this.body);
    container.append(this.el);
  }

  /** Add values at x; `series` lists the candidate keys ({key,label,scale}). */
  add(x, values, candidates) {
    if (num(x) === null) return;
    let row = this.rows.get(x);
    if (!row) this.rows.set(x, (row = {}));
    for (const c of candidates) {
      const v = num(values[c.key]);
      if (v === null) continue;
      if (this.log && v <= 0) continue;
      row[c.key] = v;
      if (!this.series.some((s) => s.key === c.key)) {
        this.series.push(c);
        this.seriesChanged = true;
      }
    }
    this.dirty = true;
  }

  data() {
    const xs = [...this.rows.keys()].sort((a, b) => a - b);
    const cols = [xs];
    for (const s of this.series) cols.push(xs.map((x) => this.rows.get(x)[s.key] ?? null));
    return cols;
  }

  width() {
    return Math.max(260, Math.floor(this.el.clientWidth || this.el.parentElement?.clientWidth || 600) - 8);
  }

  build() {
    if (this.plot) this.plot.destroy();
    this.plot = null;
    clear(this.body);
    const usesY2 = this.series.some((s) => s.scale === 'dist');
    const yScale = this.series.find((s) => s.scale && s.scale !== 'dist')?.scale || 'y';
    const axisStyle = { stroke: '#aab4c0', grid: { stroke: 'rgba(170,180,192,0.15)' }, ticks: { stroke: 'rgba(170,180,192,0.3)' } };
    const opts = {
      width: this.width(),
      height: 220,
      scales: {
        x: { time: false },
        [yScale]: this.log ? { distr: 3 } : {},
        ...(usesY2 ? { dist: {} } : {}),
      },
      axes: [
        { ...axisStyle, label: this.xLabel },
        { ...axisStyle, label: this.yLabel, scale: yScale, size: 60 },
        ...(usesY2 ? [{ ...axisStyle, label: this.y2Label, scale: 'dist', side: 1, grid: { show: false }, size: 60 }] : []),
      ],
      series: [
        { label: this.xLabel },
        ...this.series.map((s, i) => ({
          label: s.label,
          scale: s.scale === 'dist' ? 'dist' : yScale,
          stroke: PALETTE[i % PALETTE.length],
          width: 1.6,
          spanGaps: true,
          points: { show: (u) => u.data[0].length < 60, size: 4 },
        })),
      ],
      legend: { live: true },
      cursor: { drag: { x: true, y: false } },
    };
    this.plot = new uPlot(opts, this.data(), this.body);
    this.seriesChanged = false;
  }

  flush() {
    if (!this.dirty) return;
    this.dirty = false;
    const hasData = this.rows.size > 0 && this.series.length > 0;
    this.empty.hidden = hasData;
    if (!hasData) return;
    if (!this.plot || this.seriesChanged) this.build();
    else this.plot.setData(this.data());
    const cols = this.data();
    const d = this.el.dataset;
    d.points = String(this.rows.size);
    d.series = this.series.map((s) => s.key).join(',');
    d.seriesPoints = this.series.map((s, i) => cols[i + 1].filter((v) => v !== null).length).join(',');
    d.rendered = String(!!this.plot);
  }

  resize() {
    if (this.plot) this.plot.setSize({ width: this.width(), height: 220 });
  }

  destroy() {
    this.plot?.destroy();
  }
}

/**
 * The three charts of the job page. `add(records)` feeds them; redraws are batched per frame.
 * The container's `data-records` counts the records received.
 */
export class JobCharts {
  constructor(container) {
    this.container = container;
    this.sync = new Chart(container, {
      id: 'sync', title: 'Synchronisation: PSNR of L_r, L_surf and L_vol against step',
      xLabel: 'step', yLabel: 'PSNR (dB)', emptyText: 'No synchronisation records yet.',
    });
    this.error = new Chart(container, {
      id: 'error', title: 'Error against wall-clock time',
      xLabel: 'wall time (s)', yLabel: 'PSNR (dB)', y2Label: 'Chamfer',
      emptyText: 'No test evaluations yet (they need held-out views: the job option "Held-out views", '
        + 'or `nepf fit --holdout-every N` / `--eval-test DIR`).',
    });
    this.loss = new Chart(container, {
      id: 'loss', title: 'Loss terms (log scale)', xLabel: 'step', yLabel: 'loss', log: true,
      emptyText: 'No loss records yet.',
    });
    this.records = 0;
    this.raf = null;
    this.ro = new ResizeObserver(() => {
      for (const c of this.all()) c.resize();
    });
    this.ro.observe(container);
    container.dataset.records = '0';
  }

  all() {
    return [this.sync, this.error, this.loss];
  }

  add(records) {
    for (const r of records) {
      if (!r || typeof r !== 'object') continue;
      this.records++;
      const kind = r.kind || 'train';
      if (kind === 'sync' || ['psnr_r', 'psnr_surf', 'psnr_vol'].some((k) => k in r)) {
        this.sync.add(r.step, r, SYNC_KEYS);
      }
      if (kind === 'test' || ['test_psnr', 'chamfer', 'albedo_psnr'].some((k) => k in r)) {
        this.error.add(r.wall_s, r, ERR_KEYS);
      }
      const lossKeys = Object.keys(r).filter((k) => /^loss/.test(k)).sort((a, b) => (a === 'loss' ? -1 : b === 'loss' ? 1 : a.localeCompare(b)));
      if (lossKeys.length) this.loss.add(r.step, r, lossKeys.map((k) => ({ key: k, label: k })));
    }
    if (!this.raf) {
      this.raf = requestAnimationFrame(() => {
        this.raf = null;
        for (const c of this.all()) c.flush();
        this.container.dataset.records = String(this.records);
      });
    }
  }

  destroy() {
    cancelAnimationFrame(this.raf);
    this.ro.disconnect();
    for (const c of this.all()) c.destroy();
  }
}
