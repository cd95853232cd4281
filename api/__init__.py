"""NePF jobs service (FastAPI). Never imports torch, nor nepf_core beyond its stdlib-only constants
``nepf_core.limits`` (the defaults the CLI shares); see docs/SERVICE.md."""
