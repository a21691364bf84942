//! What the binaries share about their command lines and terminals.

use std::io::IsTerminal;
use std::net::{SocketAddr, ToSocketAddrs};

/// Whether log lines written to `stream` may be coloured: only when it is a
/// terminal, and not when `NO_COLOR` is set (<https://no-color.org>). Logs
/// sent to a file, a pipe or journald would otherwise carry escape codes
/// on every line.
pub fn colours_on(stream: &impl IsTerminal) -> bool {
    stream.is_terminal() && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}

/// An address to listen on: `IP:PORT` (`0.0.0.0:50051`, `[::1]:50051`), or
/// `HOST:PORT` with the first address the host name resolves to, as people
/// write `localhost:50051`.
pub fn listen_address(text: &str) -> Result<SocketAddr, String> {
    if let Ok(address) = text.parse() {
        return Ok(address);
    }
    let Some((host, port)) = text.rsplit_once(':') else {
        return Err(format!(
            "`{text}` is not HOST:PORT (such as 127.0.0.1:50051, or 0.0.0.0:50051 for every interface)"
        ));
    };
    if port.parse::<u16>().is_err() {
        return Err(format!("`{port}` in `{text}` is not a port (0 to 65535)"));
    }
    let unresolved = |why: String| format!("the host `{host}` in `{text}` has no address: {why}");
    let mut found = text.to_socket_addrs().map_err(|e| unresolved(e.to_string()))?;
    found.next().ok_or_else(|| unresolved("the resolver returned none".into()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn listen_addresses_are_ip_and_port_or_a_host_name_and_port() {
        assert_eq!(listen_address("0.0.0.0:50051"), Ok("0.0.0.0:50051".parse().unwrap()));
        assert_eq!(listen_address("[::1]:7"), Ok("[::1]:7".parse().unwrap()));
        // /etc/hosts names localhost on every machine this runs on.
        let local = listen_address("localhost:50051").unwrap();
        assert!(local.ip().is_loopback() && local.port() == 50051, "{local}");
        assert!(listen_address("localhost:http").unwrap_err().contains("`http` in `localhost:http` is not a port"));
        assert!(listen_address("localhost:70000").unwrap_err().contains("is not a port"));
        assert!(listen_address("50051").unwrap_err().contains("is not HOST:PORT"));
        assert!(listen_address("no-such-host.invalid:1").unwrap_err().contains("has no address"));
    }
}
