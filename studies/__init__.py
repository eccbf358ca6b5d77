"""Runnable studies on the library's public API (outside the package, not installed).

Each is a script, ``python -m studies.<name> --help``; the library never imports them.
"""
