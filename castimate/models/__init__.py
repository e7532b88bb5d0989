"""Symbolic physics: one small pure function per physical effect.

Every function here maps CasADi symbols (SX or MX) or numbers to CasADi expressions and has no
side effects. Problems in :mod:`castimate.problem` are compositions of these functions.
"""
