"""`python -m rngcam ...`: the `rngcam` command (rngcam.cli), for a Python without the script on its PATH."""

from rngcam.cli import main

if __name__ == "__main__":
    main(prog_name="rngcam")
