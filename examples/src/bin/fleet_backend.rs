//! `fleet-backend [URL] [VEHICLE]`: streams two minutes of a simulated vehicle to a Spoofwatch
//! server and prints its detections.

use spoofwatch_examples::{Error, fleet_backend};

#[tokio::main]
async fn main() -> Result<(), Error> {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .unwrap_or_else(|| "http://127.0.0.1:50051".to_string());
    let vehicle = args.next().unwrap_or_else(|| "example-car".to_string());
    let samples = fleet_backend::straight_drive(32.2318, -110.9092, 120);
    fleet_backend::run(&url, &vehicle, samples, &mut std::io::stdout()).await?;
    Ok(())
}
