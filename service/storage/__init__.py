"""Blob storage for uploads and artifacts (blobs), artifact records (artifacts) and retention."""
