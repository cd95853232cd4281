// Login: paste the token printed by `nepf serve` (or open its login URL, handled in main.js).
import { api, setToken, getToken } from '../api.js';
import { h } from '../util.js';

export function renderLogin(root) {
  const reason = sessionStorage.getItem('nepf.loginReason');
  sessionStorage.removeItem('nepf.loginReason');
  const msg = h('p', { class: 'error', id: 'login-error', role: 'alert', hidden: !reason }, reason || '');
  const input = h('input', {
    id: 'token', name: 'token', type: 'password', autocomplete: 'current-password',
    required: true, placeholder: 'paste the token here', value: getToken(),
    'aria-describedby': 'token-help login-error',
  });
  const submit = h('button', { type: 'submit', class: 'btn primary', id: 'login-submit' }, 'Sign in');
  const form = h('form', {
    class: 'card narrow', id: 'login-form', 'aria-labelledby': 'login-title',
    onsubmit: async (e) => {
      e.preventDefault();
      const token = input.value.trim();
      if (!token) return;
      submit.disabled = true;
      msg.hidden = true;
      setToken(token);
      try {
        await api.listJobs(); // cheapest authenticated call: checks the token
        location.hash = '#/jobs';
      } catch (err) {
        setToken('');
        msg.textContent = err.status === 401 || err.status === 403
          ? 'That token was not accepted.'
          : `Could not reach the API: ${err.message}`;
        msg.hidden = false;
        input.focus();
      } finally {
        submit.disabled = false;
      }
    },
  },
  h('h1', { id: 'login-title' }, 'Sign in'),
  h('p', { id: 'token-help', class: 'muted' },
    'Paste the API token, or open the login URL that ', h('code', {}, 'nepf serve'),
    ' prints. The token stays in this browser and is sent with every API call.'),
  h('div', { class: 'field' }, h('label', { for: 'token' }, 'API token'), input),
  msg,
  h('div', { class: 'actions' }, submit));
  root.append(form);
  input.focus();
  return () => {};
}
