//! The key of a client for the fairness and the per-client limits: its IPv4 address, or the /64
//! prefix of its IPv6 address (one IPv6 host is handed a whole /64, so a client could take any
//! number of keys from its own prefix); an IPv4-mapped IPv6 address is its IPv4 address. Keys of
//! different prefixes never collide.

use std::net::IpAddr;

/// A client's key ([`PeerKey::of`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Default)]
pub enum PeerKey {
    /// The address is not known (a connection that is not TCP, as in some tests).
    #[default]
    Unknown,
    V4(u32),
    /// The first 64 bits of the address.
    V6Prefix(u64),
}

impl PeerKey {
    /// The key of an address.
    pub fn of(ip: IpAddr) -> Self {
        match ip {
            IpAddr::V4(a) => PeerKey::V4(u32::from(a)),
            IpAddr::V6(a) => match a.to_ipv4_mapped() {
                Some(v4) => PeerKey::V4(u32::from(v4)),
                None => PeerKey::V6Prefix((u128::from(a) >> 64) as u64),
            },
        }
    }

    /// The key of an address, if any.
    pub fn of_addr(addr: Option<std::net::SocketAddr>) -> Self {
        addr.map_or(PeerKey::Unknown, |a| Self::of(a.ip()))
    }
}

impl std::fmt::Display for PeerKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PeerKey::Unknown => f.write_str("unknown"),
            PeerKey::V4(a) => write!(f, "{}", std::net::Ipv4Addr::from(*a)),
            PeerKey::V6Prefix(p) => {
                let a = std::net::Ipv6Addr::from(u128::from(*p) << 64);
                write!(f, "{a}/64")
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::net::{Ipv4Addr, Ipv6Addr};

    proptest! {
        /// Two IPv6 addresses share a key exactly when they share their /64; an IPv4 address and
        /// its mapped IPv6 form share one; no IPv6 prefix takes an IPv4 address's key.
        #[test]
        fn keys_are_prefixes_and_never_collide(a in any::<u128>(), b in any::<u128>(), v4 in any::<u32>()) {
            let (x, y) = (Ipv6Addr::from(a), Ipv6Addr::from(b));
            prop_assume!(x.to_ipv4_mapped().is_none() && y.to_ipv4_mapped().is_none());
            let same = PeerKey::of(x.into()) == PeerKey::of(y.into());
            prop_assert_eq!(same, a >> 64 == b >> 64);
            let four = Ipv4Addr::from(v4);
            prop_assert_eq!(PeerKey::of(four.into()), PeerKey::of(four.to_ipv6_mapped().into()));
            prop_assert_ne!(PeerKey::of(x.into()), PeerKey::of(four.into()));
        }
    }

    #[test]
    fn keys_print_as_addresses() {
        assert_eq!(PeerKey::of("127.0.0.9".parse().unwrap()).to_string(), "127.0.0.9");
        assert_eq!(PeerKey::of("2001:db8:1:2:3:4:5:6".parse().unwrap()).to_string(), "2001:db8:1:2::/64");
        // a XOR of the halves would give these two one key
        let victim: IpAddr = "2001:db8::1".parse().unwrap();
        let other: IpAddr = "2001:db9::1:0:1".parse().unwrap();
        assert_ne!(PeerKey::of(victim), PeerKey::of(other));
        assert_eq!(PeerKey::of_addr(None), PeerKey::Unknown);
    }
}
