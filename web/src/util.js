// Small DOM and formatting helpers shared by the views.

/**
 * Create an element: h('button', {class: 'x', onclick: fn}, 'text', child).
 * Attributes starting with "on" become listeners; `dataset` and `style` objects are merged.
 */
export function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith('on') && typeof v === 'function') el.addEventListener(k.slice(2), v);
    else if (k === 'dataset') Object.assign(el.dataset, v);
    else if (k === 'style' && typeof v === 'object') Object.assign(el.style, v);
    else if (k === 'class') el.className = v;
    else if (k in el && typeof v !== 'string') el[k] = v;
    else el.setAttribute(k, v === true ? '' : String(v));
  }
  for (const c of children.flat()) {
    if (c === undefined || c === null || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

export function clear(el) {
  while (el.firstChild) el.removeChild(el.firstChild);
  return el;
}

export function fmtDuration(s) {
  if (s === undefined || s === null || !Number.isFinite(Number(s))) return '—';
  s = Math.max(0, Math.round(Number(s)));
  if (s < 60) return `${s}s`;
  const m = Math.floor(s / 60);
  if (m < 60) return `${m}m ${String(s % 60).padStart(2, '0')}s`;
  return `${Math.floor(m / 60)}h ${String(m % 60).padStart(2, '0')}m`;
}

export function fmtTime(t) {
  if (!t) return '—';
  const d = typeof t === 'number' ? new Date(t < 1e12 ? t * 1000 : t) : new Date(t);
  if (Number.isNaN(d.getTime())) return String(t);
  return d.toLocaleString(undefined, {
    year: 'numeric', month: 'short', day: 'numeric', hour: '2-digit', minute: '2-digit', second: '2-digit',
  });
}

export function fmtBytes(n) {
  if (!Number.isFinite(n)) return '';
  if (n < 1024) return `${n} B`;
  if (n < 1024 ** 2) return `${(n / 1024).toFixed(1)} KiB`;
  if (n < 1024 ** 3) return `${(n / 1024 ** 2).toFixed(1)} MiB`;
  return `${(n / 1024 ** 3).toFixed(2)} GiB`;
}

let toastTimer = null;
export function toast(msg, kind = 'info') {
  const el = document.getElementById('toast');
  if (!el) return;
  el.textContent = msg;
  el.className = `show ${kind}`;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => (el.className = ''), 4000);
}

/** A labelled range slider; returns {wrap, input, set(v)}. */
export function slider({ id, label, min, max, step, value, onInput, format = (v) => v }) {
  const out = h('output', { for: id, id: `${id}-out` }, format(value));
  const input = h('input', {
    type: 'range', id, min, max, step, value,
    oninput: () => {
      out.textContent = format(Number(input.value));
      onInput?.(Number(input.value));
    },
  });
  const wrap = h('div', { class: 'field slider' }, h('label', { for: id }, label), input, out);
  return {
    wrap, input,
    set(v) {
      input.value = v;
      out.textContent = format(Number(v));
    },
  };
}

/** Status helpers: which states are final. */
export const FINAL_STATES = new Set(['succeeded', 'failed', 'cancelled']);
export function isFinal(status) {
  return FINAL_STATES.has(String(status || '').toLowerCase());
}

/** metrics.jsonl records -> CSV (union of keys in first-seen order; objects as JSON). */
export function metricsToCsv(records) {
  const keys = [];
  const seen = new Set();
  for (const r of records) for (const k of Object.keys(r)) if (!seen.has(k)) { seen.add(k); keys.push(k); }
  const esc = (v) => {
    if (v === undefined || v === null) return '';
    const s = typeof v === 'object' ? JSON.stringify(v) : String(v);
    return /[",\n]/.test(s) ? `"${s.replace(/"/g, '""')}"` : s;
  };
  return [keys.join(','), ...records.map((r) => keys.map((k) => esc(r[k])).join(','))].join('\n') + '\n';
}

/**
 * The file name of a Content-Disposition header (RFC 6266): `filename*` (RFC 8187, UTF-8,
 * percent-encoded) when present and readable, else the quoted or bare `filename`; null when none.
 */
export function filenameFromDisposition(header) {
  if (!header) return null;
  const star = /filename\*\s*=\s*([^;]+)/i.exec(header);
  if (star) {
    const m = /^\s*UTF-8'[^']*'(.+?)\s*$/i.exec(star[1]);
    if (m) {
      try {
        return decodeURIComponent(m[1]);
      } catch {
        // malformed percent-encoding: fall back to filename
      }
    }
  }
  const plain = /filename\s*=\s*(?:"((?:[^"\\]|\\.)*)"|([^;\s]+))/i.exec(header);
  if (!plain) return null;
  return plain[1] !== undefined ? plain[1].replace(/\\(.)/g, '$1') : plain[2];
}
