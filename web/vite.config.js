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
    // `npm run dev` proxies API calls to a running `nepf serve` (default port 8000).
    proxy: {
      '/jobs': 'http://127.0.0.1:8000',
      '/api': 'http://127.0.0.1:8000',
      '/auth': 'http://127.0.0.1:8000',
      '/health': 'http://127.0.0.1:8000',
    },
  },
});
