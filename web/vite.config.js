import { defineConfig } from 'vite';

// Relative asset paths: the API serves web/dist at "/" and the build must not assume a host.
// Everything (three.js, uPlot, fflate) is bundled from node_modules: the viewer runs offline.
export default defineConfig({
  base: './',
  build: {
    outDir: 'dist',
    emptyOutDir: true,
    chunkSizeWarningLimit: 1200,
    sourcemap: false,
  },
  server: {
    // `npm run dev` proxies API calls to a running `nepf serve` (default port 8000). The app
    // calls only the job routes (src/api.js; api/routes/jobs.py).
    proxy: {
      '/jobs': 'http://127.0.0.1:8000',
    },
  },
});
