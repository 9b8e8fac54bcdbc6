"""FastAPI front end: app factory in app.py, routes, schemas, dependencies."""
