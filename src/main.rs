fn main() -> std::process::ExitCode {
    formation::cli::main()
}
