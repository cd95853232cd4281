"""The service settings live in :mod:`jobstore.settings` (the API and the worker both read them);
this name stays for the API's own modules and for scripts that import it from here."""

from jobstore.settings import Settings, get_settings, reset_settings_cache

__all__ = ["Settings", "get_settings", "reset_settings_cache"]
