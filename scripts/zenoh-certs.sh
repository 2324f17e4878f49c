#!/usr/bin/env bash
# Makes the certificates of deploy/zenohd.json5's mutual TLS and access control (issue 16 §3): a fleet CA,
# the router's certificate (valid for the DNS name robots connect to), the map server's (CN
# "evermap-server") and one per robot (CN "<site>/<robot id>", the name the router's access control rules
# list). For trying the deploy files; in production, issue them from your own PKI and keep the CA key
# offline.
#
#   bash scripts/zenoh-certs.sh [OUT_DIR (deploy/certs)] [ROUTER_DNS (zenohd)] [ROBOT_CN ...]
#   default robots: store-1/robot-1 store-1/robot-2
set -euo pipefail
out=${1:-deploy/certs}
router_dns=${2:-zenohd}
shift $(( $# > 2 ? 2 : $# ))
robots=("$@")
[ ${#robots[@]} -gt 0 ] || robots=(store-1/robot-1 store-1/robot-2)
mkdir -p "$out"
cd "$out"
days=825
openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -days "$days" \
  -subj "/CN=evermap fleet CA" -keyout ca.key -out ca.pem \
  -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
issue() { # file, CN, subjectAltName
  openssl req -newkey ec -pkeyopt ec_paramgen_curve:P-256 -nodes -subj "/CN=${2//\//\\/}" \
    -keyout "$1.key" -out "$1.csr" 2>/dev/null
  printf 'subjectAltName=%s\nextendedKeyUsage=serverAuth,clientAuth\n' "$3" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days "$days" \
    -extfile "$1.ext" -out "$1.pem" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
  echo "$out/$1.pem  CN=$2"
}
issue zenohd zenohd "DNS:$router_dns"
issue evermap-server evermap-server "DNS:evermap-server"
for cn in "${robots[@]}"; do
  issue "${cn//\//_}" "$cn" "DNS:${cn//\//-}"
done
rm -f ca.srl
