//! argv → cli::run → exit code. The only place errors become text: one line on stderr, exit 2.

fn main() {
    let code = match edbbgen::cli::run(std::env::args_os().collect()) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("edbbgen: error: {e}");
            2
        }
    };
    std::process::exit(code);
}
