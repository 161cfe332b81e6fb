#!/bin/sh
# Certificates for the rsra Zenoh deployment (docs/deployment.md): one private CA, one
# certificate per router and per client (rig or viewer). The certificate's common name (CN)
# is the identity the routers' access-control rules match (`cert_common_names`).
#
#   make-certs.sh DIR ca                       the CA: DIR/ca.pem (give to everyone), DIR/ca-key.pem (keep offline)
#   make-certs.sh DIR router NAME HOST...      a router: DIR/NAME.pem, DIR/NAME-key.pem; HOST = DNS names or
#                                              IP addresses clients use in `tls/HOST:PORT` (checked by clients)
#   make-certs.sh DIR client NAME              a rig or viewer: DIR/NAME.pem, DIR/NAME-key.pem
#
# Keys are ECDSA P-256 (PKCS#8 PEM), written with mode 0600. Needs the openssl command (1.1.1 or 3.x).
set -eu
[ $# -ge 2 ] || { sed -n '2,12p' "$0"; exit 2; }
dir=$1 kind=$2
shift 2
umask 077
mkdir -p "$dir"
days_ca=3650
days_leaf=397

newkey() {  # $1 = key file, $2 = CSR or cert output, rest = openssl req options
    key=$1 out=$2
    shift 2
    openssl req -new -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes \
        -keyout "$key" -out "$out" "$@" 2>/dev/null
}

sign() {  # $1 = name, $2 = extensions text
    ext=$(mktemp)
    printf '%s\n' "$2" > "$ext"
    openssl x509 -req -in "$dir/$1.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca-key.pem" \
        -CAcreateserial -CAserial "$dir/ca.srl" -days "$days_leaf" -sha256 \
        -extfile "$ext" -out "$dir/$1.pem" 2>/dev/null
    rm -f "$ext" "$dir/$1.csr"
    chmod 644 "$dir/$1.pem"
}

case "$kind" in
ca)
    [ -e "$dir/ca.pem" ] && { echo "$dir/ca.pem exists; not overwritten" >&2; exit 1; }
    newkey "$dir/ca-key.pem" "$dir/ca.pem" -x509 -days "$days_ca" -sha256 -subj "/CN=rsra-zenoh-ca" \
        -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign"
    chmod 644 "$dir/ca.pem"
    ;;
router)
    [ $# -ge 2 ] || { echo "usage: $0 DIR router NAME HOST..." >&2; exit 2; }
    name=$1
    shift
    san=""
    for h in "$@"; do
        case "$h" in
        *[!0-9.]*) case "$h" in *:*) t=IP ;; *) t=DNS ;; esac ;;
        *) t=IP ;;
        esac
        san="${san:+$san,}$t:$h"
    done
    newkey "$dir/$name-key.pem" "$dir/$name.csr" -subj "/CN=$name"
    sign "$name" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=serverAuth,clientAuth
subjectAltName=$san"
    ;;
client)
    [ $# -eq 1 ] || { echo "usage: $0 DIR client NAME" >&2; exit 2; }
    name=$1
    newkey "$dir/$name-key.pem" "$dir/$name.csr" -subj "/CN=$name"
    sign "$name" "basicConstraints=critical,CA:FALSE
keyUsage=critical,digitalSignature
extendedKeyUsage=clientAuth
subjectAltName=DNS:$name"
    ;;
*)
    echo "unknown kind '$kind' (ca, router, client)" >&2
    exit 2
    ;;
esac
