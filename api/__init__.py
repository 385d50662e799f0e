"""REST API of capture-stage (FastAPI)."""
