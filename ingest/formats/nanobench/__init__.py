"""NanoBench CSV."""
