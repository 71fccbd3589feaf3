//! `fleet schema` and `fleet reference`: the mission and experiment files described by their
//! own types, and the wire protocol by its message types ([`fleet::reference`]).

use fleet::reference::{self, File};

#[derive(clap::Args, Debug)]
pub struct Args {
    /// Which file's JSON Schema to print.
    #[arg(value_enum)]
    file: File,
}

/// Print a file's JSON Schema (for an editor that checks TOML against one).
pub fn run(a: Args) -> anyhow::Result<()> {
    println!("{}", serde_json::to_string_pretty(&reference::schema(a.file))?);
    Ok(())
}

#[derive(clap::Args, Debug)]
pub struct ReferenceArgs {
    /// Which reference page to print, in Markdown (`files`: the mission and experiment files;
    /// `protocol`: the keys and messages on the wire).
    #[arg(value_enum)]
    page: Page,
}

#[derive(Debug, Clone, Copy, clap::ValueEnum)]
enum Page {
    Files,
    Protocol,
}

/// Print a reference page (`docs/reference/files.md` and `protocol.md` are this output).
pub fn reference(a: ReferenceArgs) -> anyhow::Result<()> {
    match a.page {
        Page::Files => print!("{}", reference::files_markdown()),
        Page::Protocol => print!("{}", reference::protocol_markdown()),
    }
    Ok(())
}
