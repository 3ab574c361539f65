"""Storage: the tables (`tables`), the Database handle and its migrations (`database`, `migrations/`), leases
(`leases`) and the content-addressed blob folder (`blobs`).  Import from the module that defines a name."""
