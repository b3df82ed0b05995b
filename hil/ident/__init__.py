"""The frequency-sweep identification ``hil ident`` runs (docs/ident.md), an experiment over sessions.

- :func:`ident_sweeps` (``_sweeps``): the sweep run as sessions on the closed rate loop and levelled until its
  coherence holds over the band or the drive and the travel allow no more; :class:`IdentPass` per sweep,
  :class:`IdentSweeps` for the passes, the kept one and its fit.
- :func:`run_ident` (``_run``): ``hil.api.ident``'s identification: the options checked, the session made from the
  lab's, the passes, the fit's refusals, the Bode plot and the JSON beside the log; :class:`IdentRun` is its result.

The estimation and the fit themselves are ``hil.analysis``'s. Import from here; the underscored modules are this
package's own.
"""

from hil.ident._run import MAX_EL_TRAVEL_DEG, IdentRun, run_ident
from hil.ident._sweeps import MIN_BAND_OCTAVES, IdentPass, IdentSweeps, ident_sweeps

__all__ = [
    "MAX_EL_TRAVEL_DEG",
    "MIN_BAND_OCTAVES",
    "IdentPass",
    "IdentRun",
    "IdentSweeps",
    "ident_sweeps",
    "run_ident",
]
