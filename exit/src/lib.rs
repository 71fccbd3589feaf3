//! One convention for every binary's exit: 0 done, 2 bad input or usage (a file, a field, an
//! argument the operator can fix), 1 internal failure (ours, or the machine's). The message
//! is one line on stderr, `<binary>: <what>`, naming the file or field once.
//!
//! An error is bad input when something in its chain is a [`fleet_mission::config::ConfigError`] (a
//! mission file or a node's inputs against it) or was marked with [`BadInput`] (by
//! [`bad_input`] or [`InputResult::input`]) where the input was read; everything else is
//! internal. This is the binaries' convention, so it speaks `anyhow` (a crate of its own, beside
//! the libraries, whose errors are typed; every binary depends on it).

use std::fmt;

/// Exit status: the work is done.
pub const DONE: i32 = 0;
/// Exit status: an internal failure (a bug, or the machine: disk, network, memory).
pub const INTERNAL: i32 = 1;
/// Exit status: bad input or usage (clap's usage errors use 2 as well).
pub const BAD_INPUT: i32 = 2;

/// Marks an error as the operator's input being wrong.
#[derive(Debug)]
pub struct BadInput(pub anyhow::Error);

impl fmt::Display for BadInput {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:#}", self.0)
    }
}

impl std::error::Error for BadInput {}

/// `e` as bad input.
pub fn bad_input(e: impl Into<anyhow::Error>) -> anyhow::Error {
    anyhow::Error::new(BadInput(e.into()))
}

/// `e` as bad input when `bad` (the operator's file is at fault), else as it is (internal).
pub fn bad_input_if(e: impl Into<anyhow::Error>, bad: bool) -> anyhow::Error {
    if bad {
        bad_input(e)
    } else {
        e.into()
    }
}

/// Mark a result's error as bad input.
pub trait InputResult<T> {
    fn input(self) -> anyhow::Result<T>;
}

impl<T, E: Into<anyhow::Error>> InputResult<T> for Result<T, E> {
    fn input(self) -> anyhow::Result<T> {
        self.map_err(bad_input)
    }
}

/// The exit status of an error.
pub fn code_of(e: &anyhow::Error) -> i32 {
    use fleet_math::process::{error::DatasetError, truth::TruthError};
    // A dataset that cannot be used as it is (unreadable, wrong shape, not finite, no such
    // variable) is the user's input wherever it was read; failing to write one is not. So is a
    // truth the mission's settings cannot make (a grid of 0 rows was exit 1).
    let bad_dataset = |c: &(dyn std::error::Error + 'static)| {
        c.downcast_ref::<DatasetError>()
            .is_some_and(|d| !matches!(d, DatasetError::Io { .. }))
            || c.downcast_ref::<TruthError>().is_some_and(TruthError::is_input)
    };
    if e.chain()
        .any(|c| c.is::<BadInput>() || c.is::<fleet_mission::config::ConfigError>() || bad_dataset(c))
    {
        BAD_INPUT
    } else {
        INTERNAL
    }
}

/// The error on one line: its chain joined by ": ", each link's own line breaks folded.
pub fn one_line(e: &anyhow::Error) -> String {
    let mut parts: Vec<String> = vec![];
    for c in e.chain() {
        // A BadInput shows its inner chain itself; skip the links it already printed.
        let text = c.to_string().split_whitespace().collect::<Vec<_>>().join(" ");
        if parts.last().is_some_and(|p| p.ends_with(&text)) {
            continue;
        }
        parts.push(text);
        if c.is::<BadInput>() {
            break;
        }
    }
    parts.join(": ")
}

/// Print `e` as one line after the binary's name and exit with its status.
pub fn fail(binary: &str, e: &anyhow::Error) -> ! {
    eprintln!("{binary}: {}", one_line(e));
    std::process::exit(code_of(e))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_input_is_exit_2_and_everything_else_1() {
        let e = anyhow::anyhow!("disk full");
        assert_eq!(code_of(&e), INTERNAL);
        let e = bad_input(anyhow::anyhow!("rank: must be positive")).context("mission.toml");
        assert_eq!(code_of(&e), BAD_INPUT);
        assert_eq!(one_line(&e), "mission.toml: rank: must be positive");
        let r: Result<(), std::io::Error> = Err(std::io::Error::other("x\ny"));
        assert_eq!(one_line(&r.input().unwrap_err()), "x y");
        // A truth the settings cannot make is theirs, wherever it surfaces.
        use fleet_math::process::truth::TruthError;
        let coarse = TruthError::TooCoarse {
            rows: 4,
            cols: 4,
            factor: 2,
        };
        assert_eq!(code_of(&anyhow::Error::new(coarse).context("truth")), BAD_INPUT);
    }
}
