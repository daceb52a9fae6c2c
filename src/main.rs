fn main() -> std::process::ExitCode {
    kfmc::cli::main_with(kfmc::system::Registry::builtin())
}
