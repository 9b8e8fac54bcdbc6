"""The gRPC API: the server (server) and the code generated from proto/gsa/v1/alignment.proto (generated)."""
