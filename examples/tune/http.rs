//! A small blocking HTTP/1.1 server on `std::net`: `httparse` reads the
//! request head, everything else is here, with a bound on every size and
//! wait that comes from a client.
//!
//! - One thread per connection, at most [`Limits::connections`] at once (a
//!   connection beyond them gets `503` and is closed).
//! - A request head larger than [`Limits::head_bytes`] gets `431`; a
//!   malformed one `400`; a body declared larger than [`Limits::body_bytes`]
//!   gets `413` without being read; a chunked body (`Transfer-Encoding`)
//!   `411`. Each of these closes the connection.
//! - A client that sends nothing for [`Limits::idle`] is dropped; keep-alive
//!   is supported (HTTP/1.1 unless `Connection: close`).
//! - A handler that panics answers `500`; the server goes on.

use std::io::{self, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::thread;
use std::time::Duration;

/// The bounds of what a client may send.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Largest request line plus headers, bytes.
    pub head_bytes: usize,
    /// Largest request body, bytes.
    pub body_bytes: usize,
    /// Most headers in one request.
    pub headers: usize,
    /// Most connections served at once.
    pub connections: usize,
    /// How long a connection may stay silent (or stall while sending).
    pub idle: Duration,
}

impl Default for Limits {
    fn default() -> Self {
        Limits {
            head_bytes: 16 * 1024,
            body_bytes: 64 * 1024,
            headers: 64,
            connections: 32,
            idle: Duration::from_secs(15),
        }
    }
}

/// A parsed request.
#[derive(Debug, Clone)]
pub struct Request {
    /// `GET`, `POST`, ...
    pub method: String,
    /// The path, without the query.
    pub path: String,
    /// The query string after `?` (empty if none).
    pub query: String,
    /// The body (at most [`Limits::body_bytes`]).
    pub body: Vec<u8>,
    /// The `Content-Type` header, if any.
    pub content_type: Option<String>,
    /// The `Host` header, if any.
    pub host: Option<String>,
}

impl Request {
    /// The value of `key` in the query string (`a=1&b=2`), if present.
    pub fn query_value(&self, key: &str) -> Option<&str> {
        self.query
            .split('&')
            .filter_map(|kv| kv.split_once('='))
            .find(|(k, _)| *k == key)
            .map(|(_, v)| v)
    }
}

/// A response.
#[derive(Debug, Clone)]
pub struct Response {
    /// Status code.
    pub status: u16,
    /// `Content-Type`.
    pub content_type: &'static str,
    /// The body.
    pub body: Vec<u8>,
    /// More headers (names and values of the server's own making).
    pub headers: Vec<(&'static str, String)>,
}

impl Response {
    /// A response with a body of `content_type`.
    pub fn new(status: u16, content_type: &'static str, body: impl Into<Vec<u8>>) -> Response {
        Response {
            status,
            content_type,
            body: body.into(),
            headers: Vec::new(),
        }
    }

    /// This response with one more header.
    pub fn with_header(mut self, name: &'static str, value: String) -> Response {
        self.headers.push((name, value));
        self
    }

    /// A JSON body.
    pub fn json(status: u16, value: &serde_json::Value) -> Response {
        Response::new(status, "application/json", value.to_string())
    }

    /// An error: `{"error": message}`.
    pub fn error(status: u16, message: impl Into<String>) -> Response {
        Response::json(status, &serde_json::json!({ "error": message.into() }))
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        201 => "Created",
        204 => "No Content",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        409 => "Conflict",
        411 => "Length Required",
        413 => "Payload Too Large",
        415 => "Unsupported Media Type",
        421 => "Misdirected Request",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        _ => "",
    }
}

/// A running server: its address; [`Server::stop`] (or dropping it) stops
/// accepting connections.
pub struct Server {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
    accept: Option<thread::JoinHandle<()>>,
}

impl Server {
    /// Serves `handler` on `addr` (port 0 picks a free port) in threads of
    /// its own.
    pub fn start(
        addr: &str,
        limits: Limits,
        handler: impl Fn(&Request) -> Response + Send + Sync + 'static,
    ) -> io::Result<Server> {
        let listener = TcpListener::bind(addr)?;
        let addr = listener.local_addr()?;
        let stop = Arc::new(AtomicBool::new(false));
        let handler = Arc::new(handler);
        let active = Arc::new(AtomicUsize::new(0));
        let stopping = stop.clone();
        let accept = thread::Builder::new()
            .name("http-accept".into())
            .spawn(move || {
                for stream in listener.incoming() {
                    if stopping.load(Ordering::SeqCst) {
                        break;
                    }
                    let Ok(mut stream) = stream else {
                        // Out of file descriptors, say: do not spin.
                        thread::sleep(Duration::from_millis(50));
                        continue;
                    };
                    if active.fetch_add(1, Ordering::SeqCst) >= limits.connections {
                        active.fetch_sub(1, Ordering::SeqCst);
                        let _ = write_response(
                            &mut stream,
                            &Response::error(503, "too many connections"),
                            false,
                        );
                        continue;
                    }
                    let (handler, done) = (handler.clone(), active.clone());
                    let spawned =
                        thread::Builder::new()
                            .name("http-conn".into())
                            .spawn(move || {
                                serve_connection(stream, limits, &*handler);
                                done.fetch_sub(1, Ordering::SeqCst);
                            });
                    if spawned.is_err() {
                        active.fetch_sub(1, Ordering::SeqCst);
                    }
                }
            })?;
        Ok(Server {
            addr,
            stop,
            accept: Some(accept),
        })
    }

    /// The address served.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Stops accepting connections (those open finish their request).
    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wake the accept loop.
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_secs(1));
        if let Some(h) = self.accept.take() {
            let _ = h.join();
        }
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        self.stop();
    }
}

/// What reading one request gave.
enum Read1 {
    /// A request; whether the connection stays open after it.
    Request(Request, bool),
    /// Answer this, then close.
    Refuse(Response),
    /// The client closed or went silent.
    Gone,
}

fn serve_connection(
    mut stream: TcpStream,
    limits: Limits,
    handler: &(dyn Fn(&Request) -> Response + Send + Sync),
) {
    let _ = stream.set_read_timeout(Some(limits.idle));
    let _ = stream.set_write_timeout(Some(limits.idle));
    let mut buf = Vec::with_capacity(4096);
    loop {
        match read_request(&mut stream, &mut buf, &limits) {
            Read1::Request(rq, keep) => {
                let response =
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| handler(&rq)))
                        .unwrap_or_else(|_| Response::error(500, "internal error"));
                if write_response(&mut stream, &response, keep).is_err() || !keep {
                    break;
                }
            }
            Read1::Refuse(r) => {
                let _ = write_response(&mut stream, &r, false);
                break;
            }
            Read1::Gone => break,
        }
    }
    let _ = stream.shutdown(Shutdown::Both);
}

/// Reads one request from `stream`; `buf` holds bytes already read past the
/// previous request (pipelining) and is left with those past this one.
fn read_request(stream: &mut TcpStream, buf: &mut Vec<u8>, limits: &Limits) -> Read1 {
    let mut chunk = [0u8; 4096];
    loop {
        let mut headers = vec![httparse::EMPTY_HEADER; limits.headers];
        let mut req = httparse::Request::new(&mut headers);
        match req.parse(buf) {
            Ok(httparse::Status::Complete(head_len)) => {
                let head = Head::of(&req, head_len);
                return finish_request(stream, buf, head, limits);
            }
            Ok(httparse::Status::Partial) => {}
            Err(httparse::Error::TooManyHeaders) => {
                return Read1::Refuse(Response::error(431, "too many headers"));
            }
            Err(e) => return Read1::Refuse(Response::error(400, format!("bad request: {e}"))),
        }
        if buf.len() >= limits.head_bytes {
            return Read1::Refuse(Response::error(431, "request head too large"));
        }
        match stream.read(&mut chunk) {
            Ok(0) | Err(_) => return Read1::Gone,
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
        }
        if buf.len() > limits.head_bytes {
            // Parse once more: a complete head may end within the limit.
            let mut headers = vec![httparse::EMPTY_HEADER; limits.headers];
            let mut req = httparse::Request::new(&mut headers);
            if let Ok(httparse::Status::Complete(n)) = req.parse(buf)
                && n <= limits.head_bytes
            {
                continue;
            }
            return Read1::Refuse(Response::error(431, "request head too large"));
        }
    }
}

/// A parsed request head, owned.
struct Head {
    method: Option<String>,
    target: Option<String>,
    version: Option<u8>,
    headers: Vec<(String, Vec<u8>)>,
    len: usize,
}

impl Head {
    fn of(req: &httparse::Request, len: usize) -> Head {
        Head {
            method: req.method.map(str::to_string),
            target: req.path.map(str::to_string),
            version: req.version,
            headers: req
                .headers
                .iter()
                .map(|h| (h.name.to_string(), h.value.to_vec()))
                .collect(),
            len,
        }
    }
}

fn finish_request(stream: &mut TcpStream, buf: &mut Vec<u8>, head: Head, limits: &Limits) -> Read1 {
    let (Some(method), Some(target), Some(version)) = (head.method, head.target, head.version)
    else {
        return Read1::Refuse(Response::error(400, "bad request line"));
    };
    let head_len = head.len;
    let mut content_length = 0usize;
    let mut close = version == 0;
    let (mut content_type, mut host) = (None, None);
    for (name, value) in &head.headers {
        let h = Header { name, value };
        if h.name.eq_ignore_ascii_case("content-length") {
            let Some(n) = std::str::from_utf8(h.value)
                .ok()
                .and_then(|v| v.trim().parse::<u64>().ok())
            else {
                return Read1::Refuse(Response::error(400, "bad Content-Length"));
            };
            if n > limits.body_bytes as u64 {
                return Read1::Refuse(Response::error(
                    413,
                    format!("body of {n} bytes: at most {} accepted", limits.body_bytes),
                ));
            }
            content_length = n as usize;
        } else if h.name.eq_ignore_ascii_case("transfer-encoding") {
            return Read1::Refuse(Response::error(
                411,
                "chunked bodies are not accepted: send Content-Length",
            ));
        } else if h.name.eq_ignore_ascii_case("content-type") {
            content_type = Some(String::from_utf8_lossy(h.value).into_owned());
        } else if h.name.eq_ignore_ascii_case("host") {
            host = Some(String::from_utf8_lossy(h.value).into_owned());
        } else if h.name.eq_ignore_ascii_case("connection") {
            let v = String::from_utf8_lossy(h.value).to_ascii_lowercase();
            if v.contains("close") {
                close = true;
            } else if v.contains("keep-alive") {
                close = false;
            }
        }
    }
    let (path, query) = target.split_once('?').unwrap_or((&target, ""));
    let (method, path, query) = (method.to_string(), path.to_string(), query.to_string());
    buf.drain(..head_len);
    let mut chunk = [0u8; 4096];
    while buf.len() < content_length {
        let want = (content_length - buf.len()).min(chunk.len());
        match stream.read(&mut chunk[..want]) {
            Ok(0) | Err(_) => return Read1::Gone,
            Ok(n) => buf.extend_from_slice(&chunk[..n]),
        }
    }
    let body: Vec<u8> = buf.drain(..content_length).collect();
    Read1::Request(
        Request {
            method,
            path,
            query,
            body,
            content_type,
            host,
        },
        !close,
    )
}

/// A header by reference.
struct Header<'a> {
    name: &'a str,
    value: &'a [u8],
}

fn write_response(stream: &mut TcpStream, r: &Response, keep: bool) -> io::Result<()> {
    let mut head = format!(
        "HTTP/1.1 {} {}\r\nContent-Type: {}\r\nContent-Length: {}\r\nCache-Control: no-store\r\n\
         X-Content-Type-Options: nosniff\r\nConnection: {}\r\n",
        r.status,
        reason(r.status),
        r.content_type,
        r.body.len(),
        if keep { "keep-alive" } else { "close" }
    );
    for (name, value) in &r.headers {
        head.push_str(&format!("{name}: {value}\r\n"));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes())?;
    stream.write_all(&r.body)?;
    stream.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn echo_server(limits: Limits) -> Server {
        Server::start("127.0.0.1:0", limits, |rq| {
            if rq.path == "/panic" {
                panic!("a handler bug");
            }
            Response::new(
                200,
                "text/plain",
                format!("{} {} {} {}", rq.method, rq.path, rq.query, rq.body.len()),
            )
        })
        .unwrap()
    }

    /// Sends raw bytes, returns everything the server answered until it
    /// closed (or 5 s passed).
    fn raw(addr: SocketAddr, bytes: &[u8]) -> String {
        let mut s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let _ = s.write_all(bytes);
        let mut out = Vec::new();
        let _ = s.read_to_end(&mut out);
        String::from_utf8_lossy(&out).into_owned()
    }

    fn status(answer: &str) -> u16 {
        answer
            .split(' ')
            .nth(1)
            .and_then(|s| s.parse().ok())
            .unwrap_or_else(|| panic!("no status in {answer:?}"))
    }

    #[test]
    fn answers_a_request_and_keeps_the_connection_for_the_next() {
        let srv = echo_server(Limits::default());
        let a = raw(
            srv.addr(),
            b"GET /a?x=1 HTTP/1.1\r\nHost: h\r\n\r\nPOST /b HTTP/1.1\r\nContent-Length: 3\r\nConnection: close\r\n\r\nabc",
        );
        assert_eq!(a.matches("HTTP/1.1 200 OK").count(), 2, "{a}");
        assert!(
            a.contains("GET /a x=1 0") && a.contains("POST /b  3"),
            "{a}"
        );
    }

    #[test]
    fn refuses_hostile_requests_with_a_4xx_and_stays_up() {
        let limits = Limits {
            idle: Duration::from_secs(2),
            ..Limits::default()
        };
        let srv = echo_server(limits);
        let addr = srv.addr();
        // A body declared far beyond the bound: refused unread.
        let a = raw(
            addr,
            b"POST /c HTTP/1.1\r\nContent-Length: 18446744073709551615\r\n\r\nxx",
        );
        assert_eq!(status(&a), 413, "{a}");
        let a = raw(addr, b"POST /c HTTP/1.1\r\nContent-Length: 65537\r\n\r\n");
        assert_eq!(status(&a), 413, "{a}");
        let a = raw(addr, b"POST /c HTTP/1.1\r\nContent-Length: -4\r\n\r\n");
        assert_eq!(status(&a), 400, "{a}");
        let a = raw(
            addr,
            b"POST /c HTTP/1.1\r\nTransfer-Encoding: chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n",
        );
        assert_eq!(status(&a), 411, "{a}");
        let a = raw(addr, b"\x00\x01garbage\r\n\r\n");
        assert_eq!(status(&a), 400, "{a}");
        let mut big = b"GET / HTTP/1.1\r\nX: ".to_vec();
        big.extend(std::iter::repeat_n(b'a', 20_000));
        big.extend_from_slice(b"\r\n\r\n");
        assert_eq!(status(&raw(addr, &big)), 431);
        let mut many = b"GET / HTTP/1.1\r\n".to_vec();
        for k in 0..100 {
            many.extend_from_slice(format!("X-{k}: 1\r\n").as_bytes());
        }
        many.extend_from_slice(b"\r\n");
        assert_eq!(status(&raw(addr, &many)), 431);
        // A client that stalls mid-head is dropped after the idle bound.
        let t = std::time::Instant::now();
        let a = raw(addr, b"GET / HTT");
        assert!(a.is_empty() && t.elapsed() < Duration::from_secs(5), "{a}");
        // A handler's panic is a 500, and the server still answers.
        assert_eq!(status(&raw(addr, b"GET /panic HTTP/1.1\r\n\r\n")), 500);
        let a = raw(addr, b"GET /ok HTTP/1.0\r\n\r\n");
        assert_eq!(status(&a), 200, "{a}");
    }

    #[test]
    fn connections_beyond_the_bound_get_503() {
        let limits = Limits {
            connections: 2,
            idle: Duration::from_secs(3),
            ..Limits::default()
        };
        let srv = echo_server(limits);
        let held: Vec<TcpStream> = (0..2)
            .map(|_| TcpStream::connect(srv.addr()).unwrap())
            .collect();
        thread::sleep(Duration::from_millis(200));
        let a = raw(srv.addr(), b"GET / HTTP/1.1\r\n\r\n");
        assert_eq!(status(&a), 503, "{a}");
        drop(held);
        thread::sleep(Duration::from_millis(300));
        let a = raw(srv.addr(), b"GET / HTTP/1.0\r\n\r\n");
        assert_eq!(status(&a), 200, "{a}");
    }
}
