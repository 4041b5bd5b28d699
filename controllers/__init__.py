"""Controllers: pure computation (no I/O, no clocks), reusable offline."""
