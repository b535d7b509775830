#!/usr/bin/env bash
# A private certificate authority and one certificate per mesh role, for Zenoh mutual TLS.
#
#   deploy/secure/make-certs.sh OUT_DIR [ROUTER_SAN ...]
#
# OUT_DIR/ca.pem           the authority every process trusts (root_ca_certificate)
# OUT_DIR/router.{pem,key} the router's certificate; its names (subjectAltName) are localhost, 127.0.0.1 and
#                          every ROUTER_SAN given (IP addresses or DNS names the other hosts connect to)
# OUT_DIR/{service,operator}.{pem,key}
#                          client certificates whose common names (CN) the router's access-control rules match:
#                          magmesh-service, magmesh-operator
# EXTRA_CLIENTS="name ..." also issues OUT_DIR/name.{pem,key} with CN magmesh-name: one per vehicle
#                          (vehicle-car-1 → CN magmesh-vehicle-car-1, allowed to publish car-1's raw keys only),
#                          or a second operator. `magmesh up --secure` passes the manifest's vehicles.
# What exists is kept: an existing authority (ca.pem + ca.key) signs the missing certificates, and a
# client certificate already in OUT_DIR is not issued again (delete it to renew it); the router's is.
# Keys are EC P-256, valid 825 days; ca.key stays on the machine that signs.
set -euo pipefail
out=${1:?usage: make-certs.sh OUT_DIR [ROUTER_SAN ...]}
shift
mkdir -p "$out"
cd "$out"
days=825
san="DNS:localhost,IP:127.0.0.1"
for n in "$@"; do
  if [[ $n =~ ^[0-9.]+$ ]]; then san="$san,IP:$n"; else san="$san,DNS:$n"; fi
done
if [[ ! -f ca.pem || ! -f ca.key ]]; then
  openssl ecparam -name prime256v1 -genkey -noout -out ca.key 2>/dev/null
  openssl req -x509 -new -key ca.key -sha256 -days $days -subj "/CN=magmesh-ca" -out ca.pem \
    -addext "basicConstraints=critical,CA:TRUE" -addext "keyUsage=critical,keyCertSign,cRLSign" 2>/dev/null
fi
issue() {  # name, CN, subjectAltName [always]
  if [[ -z ${4:-} && -f $1.pem && -f $1.key && $1.pem -nt ca.pem ]]; then return; fi
  openssl ecparam -name prime256v1 -genkey -noout -out "$1.key.sec1" 2>/dev/null
  openssl pkcs8 -topk8 -nocrypt -in "$1.key.sec1" -out "$1.key"
  rm -f "$1.key.sec1"
  openssl req -new -key "$1.key" -subj "/CN=$2" -out "$1.csr" 2>/dev/null
  printf 'basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature\nextendedKeyUsage=serverAuth,clientAuth\nsubjectAltName=%s\n' "$3" > "$1.ext"
  openssl x509 -req -in "$1.csr" -CA ca.pem -CAkey ca.key -CAcreateserial -days $days -sha256 \
    -extfile "$1.ext" -out "$1.pem" 2>/dev/null
  rm -f "$1.csr" "$1.ext"
}
issue router magmesh-router "$san" always  # its names may change with the arguments
for role in service operator ${EXTRA_CLIENTS:-}; do
  issue "$role" "magmesh-$role" "DNS:magmesh-$role"
done
chmod 600 ./*.key
echo "certificates in $(pwd): ca.pem router service operator ${EXTRA_CLIENTS:-}"
