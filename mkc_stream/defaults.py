"""The one default window (samples kept) and E-step interval of the library, the C port's host build
and every command. Standard library only, so the command line can import it without numpy.

A firmware build's window is at most its compiled capacity MKC_W (256 by default, for the memory of
a small MCU), so there the default is min(MKC_W, DEFAULT_WINDOW).
"""
DEFAULT_WINDOW = 512
DEFAULT_ESTEP_EVERY = 32
