"""l3d_app entry point: ``python main.py task=<name> key=value ...`` (Hydra)."""

import os
import sys

import hydra
from omegaconf import DictConfig


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg: DictConfig):
    from l3d_app.app import run

    return run(cfg)


def cli() -> None:
    """``main()`` on the command line, its shorthands expanded (:mod:`l3d_app.aliases`), with Hydra's own
    errors (a typo'd key, an unknown option of a config group, a malformed override) and the file system's
    (a run directory that cannot be made or written) reported like every other bad input: one line on
    stderr, exit status 2. A sweep runs all its
    jobs; one line per job with bad input, then a summary line and exit status 2.
    ``L3D_DEBUG=1`` leaves them to Hydra's report or the traceback."""
    from hydra.errors import CompactHydraException

    from l3d_app.aliases import expand_aliases

    sys.argv[1:] = expand_aliases(sys.argv[1:])     # beta=0.1 -> density.beta=0.1 (task=volsdf)
    if os.environ.get("L3D_DEBUG", "").strip() in ("", "0"):
        os.environ["HYDRA_FULL_ERROR"] = "1"   # Hydra raises instead of printing a report and exiting 1
    from l3d_app.sweep_jobs import SweepJobFailed, remove_empty_sweep_dirs, summary_line, without_job_error_echo

    try:
        with without_job_error_echo():
            main()
    except SweepJobFailed as err:    # the sweep's other jobs ran; each failed job printed its line
        print(f"l3d_app: error: {summary_line(err, none_ran=remove_empty_sweep_dirs())}", file=sys.stderr)
        sys.exit(2)
    except CompactHydraException as err:
        from l3d_app.app import config_error_line

        print(f"l3d_app: error: {config_error_line(err)}", file=sys.stderr)
        sys.exit(2)
    except ValueError as err:    # Hydra's own command-line conflicts (-m with --cfg); a run's errors end in app.run
        if os.environ.get("L3D_DEBUG", "").strip() not in ("", "0"):
            raise
        print(f"l3d_app: error: {' '.join(str(err).split())}", file=sys.stderr)
        sys.exit(2)
    except OSError as err:       # the file system refused: a run directory that is a file, no permission, disk full
        if os.environ.get("L3D_DEBUG", "").strip() not in ("", "0"):
            raise
        where = f": {err.filename}" if err.filename else ""
        print(f"l3d_app: error: {err.strerror or err}{where} (the file system refused: check hydra.run.dir, "
              f"permissions, free space)", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    cli()
