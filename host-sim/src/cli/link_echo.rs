//! `harmonic-sim link-echo`: the far end of a TCP depth link, sending every byte back.

/// The flags of `link-echo`.
#[derive(clap::Args)]
pub struct LinkEchoArgs {
    /// Listen on HOST:PORT for `explore --link tcp:HOST:PORT` (one connection, then exit).
    #[arg(long, conflicts_with = "connect", required_unless_present = "connect")]
    listen: Option<String>,
    /// Connect to `explore --link tcp-listen:HOST:PORT` instead.
    #[arg(long)]
    connect: Option<String>,
}

/// Run `link-echo`: accept or make one TCP connection and send every byte back until it closes.
pub fn run(args: &LinkEchoArgs) -> Result<(), String> {
    let stream = match (&args.listen, &args.connect) {
        (Some(addr), _) => {
            let listener = std::net::TcpListener::bind(addr).map_err(|e| format!("--listen {addr}: {e}"))?;
            eprintln!("link-echo: listening on {addr}");
            listener
                .accept()
                .map(|(s, _)| s)
                .map_err(|e| format!("--listen {addr}: {e}"))?
        }
        (None, Some(addr)) => {
            std::net::TcpStream::connect(addr).map_err(|e| format!("--connect {addr}: {e}"))?
        }
        (None, None) => return Err("give --listen HOST:PORT or --connect HOST:PORT".into()),
    };
    let bytes = harmonic_sim::link::transport::echo(stream).map_err(|e| format!("link-echo: {e}"))?;
    eprintln!("link-echo: {bytes} bytes sent back");
    Ok(())
}
