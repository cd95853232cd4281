// Entry point: login-URL handling and the hash router.
import './style.css';
import 'uplot/dist/uPlot.min.css';
import { getToken, setToken } from './api.js';
import { h, clear } from './util.js';
import { renderLogin } from './views/login.js';
import { renderJobs } from './views/jobs.js';
import { renderUpload } from './views/upload.js';
import { renderJob } from './views/job.js';

/**
 * The login URL printed by `nepf serve` carries the token in the fragment
 * (`/#token=...`), so it never reaches server logs. Store it and drop it from the URL.
 */
function consumeLoginFragment() {
  const m = location.hash.match(/[#&?]token=([^&]+)/);
  if (m) {
    setToken(decodeURIComponent(m[1]));
    history.replaceState(null, '', `${location.pathname}${location.search}#/jobs`);
    return true;
  }
  // Also accept ?token= in the query string (some terminals drop fragments).
  const q = new URLSearchParams(location.search);
  if (q.get('token')) {
    setToken(q.get('token'));
    q.delete('token');
    const s = q.toString();
    history.replaceState(null, '', `${location.pathname}${s ? `?${s}` : ''}#/jobs`);
    return true;
  }
  return false;
}

let cleanup = null;
const main = document.getElementById('main');

function renderAuthBox() {
  const box = document.getElementById('auth-box');
  clear(box);
  if (getToken()) {
    box.append(
      h('span', { class: 'muted small', id: 'auth-state' }, 'Signed in'),
      h('button', {
        type: 'button', class: 'btn ghost small', id: 'logout',
        onclick: () => {
          setToken('');
          location.hash = '#/login';
        },
      }, 'Sign out'),
    );
  } else {
    box.append(h('a', { href: '#/login', class: 'btn ghost small' }, 'Sign in'));
  }
}

function route() {
  if (cleanup) {
    try {
      cleanup();
    } catch (e) {
      console.warn('view cleanup failed', e);
    }
    cleanup = null;
  }
  clear(main);
  renderAuthBox();
  const hash = location.hash.replace(/^#/, '') || '/jobs';
  const parts = hash.split('/').filter(Boolean);
  for (const a of document.querySelectorAll('[data-nav]')) {
    a.toggleAttribute('aria-current', a.dataset.nav === parts[0] || (a.dataset.nav === 'jobs' && parts[0] === 'job'));
  }
  if (!getToken() && parts[0] !== 'login') {
    location.replace('#/login');
    return;
  }
  document.body.dataset.route = parts[0] || 'jobs';
  switch (parts[0]) {
    case 'login':
      cleanup = renderLogin(main);
      break;
    case 'upload':
      cleanup = renderUpload(main);
      break;
    case 'job':
    case 'jobs':
      if (parts[1]) cleanup = renderJob(main, decodeURIComponent(parts[1]));
      else cleanup = renderJobs(main);
      break;
    default:
      cleanup = renderJobs(main);
  }
}

window.addEventListener('nepf:unauthorized', () => {
  if (!location.hash.startsWith('#/login')) {
    sessionStorage.setItem('nepf.loginReason', 'Your token was rejected. Paste a valid token.');
    location.hash = '#/login';
  }
});

window.addEventListener('hashchange', () => {
  consumeLoginFragment(); // replaceState does not fire hashchange, so route now either way
  route();
});

consumeLoginFragment();
route();
