"""Digital twin: fit the emulated plant to a platform's session logs (``hil fit``) or to published figures."""
