"""The library's error base: every error gsa/ raises on purpose derives from GSAError.

`except GSAError` handles any failure the library reports (a file it cannot read, a model
it cannot use, image sets it cannot reconstruct, a service answer); the `gsa` command prints
each as one `gsa: error:` line. Each kind keeps the built-in base it had, ValueError for input
the library refuses and RuntimeError for work that failed, so `except ValueError` still holds.

The kinds live beside the code that raises them (gsa.io.ply.PlyError, gsa.recon.sfm.SfMError,
gsa.client.ServiceError, ...); tests/test_errors.py checks that each derives from GSAError.
This module imports nothing, so catching the base loads none of them.
"""

from __future__ import annotations


class GSAError(Exception):
    """Base of the errors the library raises on purpose; the message is one line for the user."""
