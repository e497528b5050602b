"""`python -m bimfactor` runs the `bimfactor` command."""

from bimfactor.cli import app

if __name__ == "__main__":
    app(prog_name="bimfactor")
