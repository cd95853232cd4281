"""NePF jobs service (FastAPI). Never imports torch or nepf_core; see docs/SERVICE.md."""
