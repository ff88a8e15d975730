"""The HTTP endpoint (/metrics, /healthz, /readyz, /status), its guard, the console and
the trace stream."""
