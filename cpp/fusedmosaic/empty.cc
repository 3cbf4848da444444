// Placeholder translation unit while the core is header-only.
