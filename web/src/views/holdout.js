// "A held-out view while it trains": the picture of the latest held-out evaluation
// (RUN/holdout/latest.png, written by nepf_core/holdout_preview.py: render | ground truth |
// error) beside the error chart, so the object shows long before the export.
//
// DOM state (read by tests): `figure#holdout-preview` is hidden until a `kind: "test"` record
// names a `preview`; then its data-step is the step of the evaluation shown and its <img> holds
// that picture (fetched with the auth header, no-store: every evaluation rewrites the same path).
import { api } from '../api.js';
import { h } from '../util.js';

/** The newest `kind: "test"` record of `records` that names a preview picture, or null. */
export function latestPreview(records) {
  let best = null;
  for (const r of records) {
    if (r && r.kind === 'test' && typeof r.preview === 'string' && (!best || r.step >= best.step)) best = r;
  }
  return best;
}

export class HoldoutPreview {
  /** @param {string} jobId */
  constructor(jobId) {
    this.jobId = jobId;
    this.step = -1;
    this.url = null;
    this.img = h('img', { class: 'holdout-img', alt: 'Held-out view 0: render, ground truth and error' });
    this.caption = h('figcaption', { class: 'small muted' }, '');
    this.el = h('figure', { class: 'holdout-preview', id: 'holdout-preview', hidden: true, dataset: { step: '' } },
      this.img, this.caption);
  }

  /** Show the newest preview among `records` (a batch of metrics records) if it is newer. */
  async update(records) {
    const rec = latestPreview(records);
    if (!rec || rec.step <= this.step) return;
    this.step = rec.step;
    try {
      const blob = await api.artifactBlob(this.jobId, rec.preview, undefined, 'no-store');
      if (rec.step !== this.step) return;   // a newer one arrived meanwhile
      if (this.url) URL.revokeObjectURL(this.url);
      this.url = URL.createObjectURL(blob);
      this.img.src = this.url;
      this.caption.textContent = `Held-out view 0 at step ${rec.step}: render | ground truth | error (×4)`;
      this.el.dataset.step = String(rec.step);
      this.el.hidden = false;
    } catch (e) {
      console.warn('held-out preview:', e.message);
    }
  }

  dispose() {
    if (this.url) URL.revokeObjectURL(this.url);
    this.url = null;
  }
}
