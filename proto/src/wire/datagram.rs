//! One decode for every kind of datagram on the wire: [`Datagram::decode`]
//! tells the kind by its magic ([`Kind::of`]) and checks the format behind
//! it, giving a view that borrows from the datagram (nothing is copied).
//! Encoding stays with each format (`Packet::encode`, `BatchBuilder`,
//! `Fragment::encode`, `Sealer`).

use super::batch::Batch;
use super::fragment::Fragment;
use super::sealed::Sealed;
use super::{DecodeError, Kind, Packet};

/// A checked view of one datagram.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Datagram<'a> {
    /// A Pulicast 2.x packet.
    Packet(Packet<'a>),
    /// A batch of messages of one channel.
    Batch(Batch<'a>),
    /// A fragment of a large message.
    Fragment(Fragment<'a>),
    /// A sealed datagram: its header (the inside is the opener's).
    Sealed(Sealed<'a>),
    /// Discovery gossip, whole (its format is `pulicast_discovery::wire`'s).
    Discovery(&'a [u8]),
}

impl<'a> Datagram<'a> {
    /// Checks `datagram` as the kind its magic says. A datagram with no
    /// known magic is an error ([`DecodeError::BadMagic`], or
    /// [`DecodeError::TooShort`] if shorter than a packet).
    pub fn decode(datagram: &'a [u8]) -> Result<Self, DecodeError> {
        Ok(match Kind::of(datagram) {
            Kind::Batch => Datagram::Batch(Batch::decode(datagram)?),
            Kind::Fragment => Datagram::Fragment(Fragment::decode(datagram)?),
            Kind::Sealed => Datagram::Sealed(Sealed::decode(datagram)?),
            Kind::Discovery => Datagram::Discovery(datagram),
            // Unknown magics too: the packet decoder says what is wrong.
            Kind::Packet | Kind::Unknown => Datagram::Packet(Packet::decode(datagram)?),
        })
    }

    /// Its kind.
    pub fn kind(&self) -> Kind {
        match self {
            Datagram::Packet(_) => Kind::Packet,
            Datagram::Batch(_) => Kind::Batch,
            Datagram::Fragment(_) => Kind::Fragment,
            Datagram::Sealed(_) => Kind::Sealed,
            Datagram::Discovery(_) => Kind::Discovery,
        }
    }

    /// The channel it names: every kind but gossip names one.
    pub fn channel(&self) -> Option<&'a str> {
        match self {
            Datagram::Packet(p) => Some(p.channel),
            Datagram::Batch(b) => Some(b.channel),
            Datagram::Fragment(f) => Some(f.channel),
            Datagram::Sealed(s) => Some(s.channel),
            Datagram::Discovery(_) => None,
        }
    }
}
