"""The browser results page: previews (preview.py), the HTML page (page.py), the
local server behind `gsa view` (local.py) and the built Spark viewer (static/)."""
