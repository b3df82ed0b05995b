"""Board emulators for the bench: the boards of the lab on pseudo-terminals.

They share nothing with `hil` but the protocol definitions (`hil.protocol`).
"""
