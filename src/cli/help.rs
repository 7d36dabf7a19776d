//! The examples and exit statuses of `--help` and the man pages: one text per subcommand, on
//! the shipped inputs (the bundled NJ-130 cell, examples/); a test parses every example.

/// The paths the examples use, relative to a checkout.
macro_rules! nj130 {
    () => {
        "robots/comau_nj130/robot.dh.toml"
    };
}
macro_rules! cell {
    () => {
        "robots/comau_nj130/cell.toml"
    };
}

pub const COMPILE: &str = concat!(
    "Examples:\n",
    "  # The measurement program for the bundled NJ-130 cell, with its report and page\n",
    "  edbbgen ",
    nj130!(),
    " --cell ",
    cell!(),
    " -o nj130.nc --json nj130.json --html nj130.html\n",
    "  # The same robot, the fixture position and the MAP given on the command line, for a KUKA\n",
    "  edbbgen ",
    nj130!(),
    " --fixture 258,1468,708 --tool 0,0,100 --dialect krl -o EDBB.src\n",
    "  # Golden-file check in CI: exit 1 and a diff when the program would change\n",
    "  edbbgen ",
    nj130!(),
    " --cell ",
    cell!(),
    " -o nj130.nc --check\n",
);

pub const MODEL: &str = concat!(
    "Examples:\n",
    "  # Which of the 30 parameters a bar at this fixture can identify\n",
    "  edbbgen model ",
    nj130!(),
    " --fixture 258,1468,708 --tool 60,30,120\n",
    "  # The report as JSON on stdout, for a script\n",
    "  edbbgen model ",
    nj130!(),
    " --cell ",
    cell!(),
    " --json -\n",
);

pub const VERIFY: &str = concat!(
    "Examples:\n",
    "  # Re-check a compiled (or hand-edited) program against the cell\n",
    "  edbbgen verify ",
    nj130!(),
    " nj130.nc --cell ",
    cell!(),
    "\n",
    "  # Check a recorded dry run (joint log) against the program it ran\n",
    "  edbbgen verify ",
    nj130!(),
    " nj130.nc --cell ",
    cell!(),
    " --trace dryrun.csv\n",
);

pub const SIMULATE: &str = concat!(
    "Examples:\n",
    "  # What the bar would read running nj130.nc on a robot with these errors\n",
    "  edbbgen simulate ",
    nj130!(),
    " nj130.nc --truth examples/nj130/truth.toml -o measured.csv\n",
    "  # A dry run: the bar's own log and the controller's joint log\n",
    "  edbbgen simulate ",
    nj130!(),
    " nj130.nc --truth examples/nj130/truth.toml -o dry.csv --bar-log bar.csv --joint-log dryrun.csv\n",
);

pub const DIAGNOSE: &str = concat!(
    "Examples:\n",
    "  # Where the model and the measurement disagree, and the effect that explains it\n",
    "  edbbgen diagnose ",
    nj130!(),
    " --fixture 258,1468,708 --measured measured.csv --json diagnose.json --html diagnose.html\n",
    "  # Static readings of an instrument stated at 15 µm\n",
    "  edbbgen diagnose ",
    nj130!(),
    " --fixture 258,1468,708 --measured measured.csv --noise 15\n",
);

pub const CIRCLE: &str = concat!(
    "Examples:\n",
    "  # The ISO 230-4 circle test at the paper's fixture\n",
    "  edbbgen circle ",
    nj130!(),
    " --fixture 258,1468,708 -o circle.nc\n",
);

pub const LDBB: &str = concat!(
    "Examples:\n",
    "  # Compliance and stiffness from loaded circle data, checked against a laser tracker\n",
    "  edbbgen ldbb loaded.csv --setup examples/ldbb/setup.toml --reference lt.csv --json ldbb.json --html ldbb.html\n",
);

pub const LDBB_CIRCLE: &str = concat!(
    "Examples:\n",
    "  # The loaded circle test of the set-up (the paper's, on the ABB IRB 6700 of ../shared/robots)\n",
    "  edbbgen ldbb-circle ../shared/robots/abb_irb6700_200_260/robot.urdf --setup examples/ldbb/setup.toml -o ldbb.nc\n",
);

pub const SIMULATE_LDBB: &str = concat!(
    "Examples:\n",
    "  # Loaded circle data and a tracker reference from a known truth\n",
    "  edbbgen simulate-ldbb --setup examples/ldbb/setup.toml --truth examples/ldbb/truth.toml -o loaded.csv --reference lt.csv\n",
);

pub const DIALECTS: &str = concat!(
    "Examples:\n",
    "  # The controller languages, and what each approximates\n",
    "  edbbgen dialects\n",
    "  # The same as JSON, to a file\n",
    "  edbbgen dialects --json dialects.json\n",
);

pub const CALIBRATE: &str = concat!(
    "Examples:\n",
    "  # A calibrated robot file from one measured run, with its report and page\n",
    "  edbbgen calibrate ",
    nj130!(),
    " --measured measured.csv --fixture 258,1468,708 -o nj130.cal.dh.toml --json cal.json --html cal.html\n",
    "  # From the bar's own log and the program that ran (stop-and-measure)\n",
    "  edbbgen calibrate ",
    nj130!(),
    " --bar-log bar.csv --program nj130.nc -o nj130.cal.dh.toml --json cal.json\n",
    "  # Later: what moved since the calibration in cal.json\n",
    "  edbbgen calibrate ",
    nj130!(),
    " --measured check.csv --fixture 258,1468,708 -o now.dh.toml --baseline cal.json\n",
);

pub const PLACE: &str = concat!(
    "Examples:\n",
    "  # The best fixture positions in the cell, two of them for a campaign\n",
    "  edbbgen place ",
    nj130!(),
    " --cell ",
    cell!(),
    " --grid 5,5,3 --count 2 --write-cell placed\n",
);

pub const COMPENSATE: &str = concat!(
    "Examples:\n",
    "  # Compensated joint and Cartesian targets from a calibration\n",
    "  edbbgen compensate nj130.cal.dh.toml --nominal ",
    nj130!(),
    " --targets examples/nj130/targets.csv -o targets.comp.csv --calibration cal.json\n",
    "  # A compensated program, checked against the cell\n",
    "  edbbgen compensate nj130.cal.dh.toml --nominal ",
    nj130!(),
    " --program examples/nj130/pick.nc -o pick.comp.nc --cell ",
    cell!(),
    " --calibration cal.json\n",
);

pub const COMPLETIONS: &str = concat!(
    "Examples:\n",
    "  edbbgen completions bash > ~/.local/share/bash-completion/completions/edbbgen\n",
    "  edbbgen completions zsh > ~/.zfunc/_edbbgen\n",
);

pub const MAN: &str = concat!(
    "Examples:\n",
    "  edbbgen man | man -l -\n",
    "  edbbgen man calibrate | man -l -\n",
);

/// The EXIT STATUS section of every man page (the reference: docs/reference/exit-codes.md).
pub const EXIT_STATUS: &str = "\
0  success.
1  a check failed, and the output says why: verify found a violation, --check found a \
difference, calibrate could determine neither the robot nor the set-up, compensate could not \
compensate a move, a compiled program failed its own verify (nothing is written).
2  bad input or usage: one line on stderr names the file, the field or the flag; no output \
file is written.
3  calibrate only: the geometry is confirmed within the stated bound of nominal, and the \
set-up (MAP, fixtures, length zeros) is fitted and written.";

/// Every subcommand's examples, by name (`None`: the compiler).
pub fn examples(subcommand: Option<&str>) -> Option<&'static str> {
    Some(match subcommand? {
        "model" => MODEL,
        "verify" => VERIFY,
        "simulate" => SIMULATE,
        "diagnose" => DIAGNOSE,
        "circle" => CIRCLE,
        "ldbb" => LDBB,
        "ldbb-circle" => LDBB_CIRCLE,
        "simulate-ldbb" => SIMULATE_LDBB,
        "dialects" => DIALECTS,
        "calibrate" => CALIBRATE,
        "place" => PLACE,
        "compensate" => COMPENSATE,
        "completions" => COMPLETIONS,
        "man" => MAN,
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::args::Cli;
    use clap::{CommandFactory, Parser};

    /// Every example line, as argv (the examples use no quoting; a pipe or a redirection ends
    /// the command).
    fn commands(text: &str) -> Vec<Vec<&str>> {
        text.lines()
            .map(str::trim)
            .filter(|l| l.starts_with("edbbgen"))
            .map(|l| {
                l.split_whitespace()
                    .take_while(|w| !matches!(*w, "|" | ">"))
                    .collect()
            })
            .collect()
    }

    #[test]
    fn every_subcommand_has_examples_that_parse_with_todays_flags() {
        let cli = Cli::command();
        let mut texts = vec![(None, COMPILE)];
        for sub in cli.get_subcommands() {
            let name = sub.get_name();
            let text = examples(Some(name)).unwrap_or_else(|| panic!("{name}: no examples"));
            assert_eq!(
                sub.get_after_help().map(|h| h.to_string()).as_deref(),
                Some(text),
                "{name}: --help shows its examples"
            );
            texts.push((Some(name), text));
        }
        for (name, text) in texts {
            let list = commands(text);
            assert!(!list.is_empty(), "{name:?}: no example command");
            for argv in list {
                if let Some(n) = name {
                    assert_eq!(argv.get(1), Some(&n), "{n}: an example of another command");
                }
                if let Err(e) = Cli::try_parse_from(&argv) {
                    panic!("{name:?}: {} does not parse: {e}", argv.join(" "));
                }
            }
        }
        // The check can fail: a flag that does not exist is refused.
        assert!(Cli::try_parse_from(["edbbgen", "model", "r.dh.toml", "--no-such-flag"]).is_err());
    }
}
