//! The binary a study runs in: kfmc's own command, or a plugin crate's binary that calls
//! [`crate::cli::main_as`] with a [`Program`] of its own.

/// A binary's name and version. A plugin crate's binary names itself with one
/// ([`crate::cli::main_as`]): its `--help` and `--version`, the headers of `check` and `tune`,
/// the `manifest.toml` it writes and the report's "reproduce" line then name it, while kfmc's
/// library version (what `merge` and `resume` compare) is recorded beside it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Program {
    /// The binary's name, as a user types it (`env!("CARGO_BIN_NAME")` or the crate's name).
    pub name: &'static str,
    /// The binary's version (`env!("CARGO_PKG_VERSION")`).
    pub version: &'static str,
}

impl Program {
    /// kfmc's own command.
    pub const KFMC: Program = Program {
        name: "kfmc",
        version: env!("CARGO_PKG_VERSION"),
    };
}

impl Default for Program {
    fn default() -> Self {
        Program::KFMC
    }
}
