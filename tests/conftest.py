"""pytest set-up shared by every test.

The tests mirror the package (tests/geometry/ tests rotonly_cli/geometry/, ...); test file
names are unique across folders (pytest's default import mode needs that without
__init__.py files). This file puts its folder on sys.path (pytest's rootdir conftest), so
every test imports the shared helpers as ``from helpers import ...``: the bundled fixtures'
path (the tests read data_fixtures/ only) and the simulated scenes of the geometry tests.
"""
