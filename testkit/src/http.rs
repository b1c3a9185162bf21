//! A parsed HTTP response, shared by the raw-socket HTTP clients of the server's and the
//! end-to-end tests (each parses its own wire format into it).

/// One response.
#[derive(Debug)]
pub struct Response {
    /// Status code.
    pub status: u16,
    /// Header fields in order.
    pub headers: Vec<(String, String)>,
    /// The body (de-chunked).
    pub body: Vec<u8>,
}

impl Response {
    /// The first header field named `name` (case-insensitive).
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(n, _)| n.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// The body as UTF-8 text.
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

/// Answers on `stream` with a 100,000-byte body sent one byte every 50 ms (the head at
/// once): a server that is never idle long enough for a progress timeout, for testing
/// overall request deadlines. Returns when the peer goes away.
pub fn trickle_answer(stream: &mut impl std::io::Write) {
    if stream
        .write_all(b"HTTP/1.1 200 OK\r\nContent-Length: 100000\r\n\r\n")
        .is_err()
    {
        return;
    }
    for _ in 0..100_000 {
        if stream.write_all(b"x").is_err() {
            return;
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}
