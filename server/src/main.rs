//! `quincunx-server`: the server alone (no codec linked), for containers. The same as
//! `quincunx serve`.

use clap::Parser;

/// Serve quincunx repositories over HTTP/1.1 and HTTP/2.
#[derive(Parser)]
#[command(version)]
struct Cli {
    #[command(flatten)]
    serve: quincunx_server::ServeArgs,
    /// Log filter (tracing `EnvFilter` syntax), e.g. `info` or `quincunx_server=debug`.
    #[arg(long, env = "QUINCUNX_LOG", default_value = "info")]
    log: String,
}

fn main() -> std::process::ExitCode {
    let cli = Cli::parse();
    tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::new(&cli.log))
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    match quincunx_server::run_cli(&cli.serve, |addr, scheme| {
        tracing::info!("serving on {scheme}://{addr}/ (repositories: {scheme}://{addr}/repos)");
    }) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}
