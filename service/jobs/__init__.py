"""Jobs: the job record and its options, input checks, admission (quotas, memory),
submission shared by REST and gRPC (core), and N-way jobs (many)."""
