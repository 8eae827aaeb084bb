//! `alarm-watcher [URL] [CURSOR]`: follows a Spoofwatch server's alarm events after CURSOR (every
//! stored event with 0; only new ones without), until interrupted.

use spoofwatch_examples::{Error, alarm_watcher};

#[tokio::main]
async fn main() -> Result<(), Error> {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .unwrap_or_else(|| "http://127.0.0.1:50051".to_string());
    let cursor = args.next().map(|c| c.parse::<i64>()).transpose()?;
    alarm_watcher::run(&url, cursor, false, &mut std::io::stdout()).await?;
    Ok(())
}
