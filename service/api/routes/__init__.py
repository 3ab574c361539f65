"""HTTP routers, one per resource: flights, models, jobs, evaluations, diagnoses."""
