fn main() -> std::process::ExitCode {
    kfmc::cli::main_with(kfmc::systems::builtin())
}
