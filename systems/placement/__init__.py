"""Stage 2, instrument placement: the feeding target and the virtual fixture, with the
fast (bound) and exact (FCL) tool-to-tissue clearances they are checked by."""
