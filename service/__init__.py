"""GSA alignment service: HTTP + gRPC job API, job store, queue, workers, storage.

`service` imports `gsa`; `gsa` never imports `service` (the CLI does it lazily).
"""
