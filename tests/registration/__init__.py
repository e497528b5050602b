"""Tests of bimfactor.registration."""
