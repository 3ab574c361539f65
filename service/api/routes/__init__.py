"""The JSON routes (FastAPI routers), one module per resource: flights, models, jobs, evaluations, diagnoses."""
