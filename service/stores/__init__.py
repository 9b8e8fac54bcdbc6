"""Job stores behind one interface (base): Redis (distributed mode) and SQLite (embedded mode)."""
