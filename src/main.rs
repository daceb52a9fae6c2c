use clap::Parser;

fn main() -> std::process::ExitCode {
    kfmc::cli::main_with(kfmc::cli::Cli::parse())
}
